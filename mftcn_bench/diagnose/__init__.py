"""Diagnostics of the harness's own results, as `mftcn-bench diagnose ...`: questions a result raises that its
record cannot answer. `coverage` asks where the cart is in each camera's image of a cartpole data set
(projection geometry, nothing rendered); `state_probe` asks how much of the true state an encoder's embedding
of each camera carries on held-out data (and, for expert demonstrations, off them); `policy_range` replays a
finished control run's stored policy on its test environments and asks where it drives the cart, whether the
camera sees it there and how well the state probe reads the frames the policy meets. Each returns dataclasses;
the command line (`cli.diagnose_commands`) prints them. This layer sits above a run (it plans, loads and fits
through `run.plan` and `run.artifacts`, as a run does) and below the sweeps and the command line.
"""
