"""The paper's five result tables as data: rows (label, our encoder and task, a config filter), metric
columns, and the paper's published figures; and tables of our own: `swingup-limits` and `cheetah-limits`, the
PPO-limit analyses (what keeps PPO on an embedding below PPO on true state), the encoder's streams of frames
and behaviour cloning.

This module is the one place where the paper's numbers are written down (from
"Learning Actionable Representations from Visual Observations", tables `table_regression`,
`table_cartpole`, the cheetah table, `table:mftcn_pouring` and `table:mftcn_pouring_details`).
A paper figure of None is a "-" in the paper; a row whose `paper` is None is not in the paper.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from mftcn_bench.data.cartpole import TARGETS
from mftcn_bench.results.selection import VARIED


@dataclass(frozen=True)
class MetricColumn:
    """A stored metric shown as one column."""

    metric: str
    label: str


@dataclass(frozen=True)
class PaperRow:
    """One row of a paper table: its label cells, the encoder and task whose stored runs fill it, the
    config values those runs must have (dotted keys), and the paper's figures, one per metric column."""

    labels: tuple[str, ...]
    encoder: str
    task: str
    where: Mapping[str, Any] = field(default_factory=dict)
    paper: tuple[float | None, ...] | None = None


@dataclass(frozen=True)
class PaperTable:
    name: str
    title: str
    label_headers: tuple[str, ...]
    columns: tuple[MetricColumn, ...]
    rows: tuple[PaperRow, ...]
    note: str = ""
    decimals: int = 4
    # Config keys whose overridden values a run may have and still count (each value is its own row).
    varied: tuple[str, ...] = VARIED
    # Whether runs that no row covers follow as "(not in paper)" rows. False for a table of chosen analyses,
    # whose tasks' other runs (other encoders) are rows of the paper tables already.
    other_runs: bool = True

    @property
    def tasks(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(row.task for row in self.rows))


# --- Table "Results on regressing Cartpole Positions and Velocities from mfTCN Embeddings" -------------
_PROBE_PAPER: dict[tuple[int, int], tuple[float, ...]] = {  # (embedding, lookback) -> columns in order
    (8, 1): (0.1312, 0.0201, 0.2979, 0.0238, 0.0085, 0.0279, 0.4964, 0.0993),
    (8, 2): (0.0435, 0.0017, 0.1062, 0.0011, 0.0025, 0.0016, 0.1587, 0.0537),
    (8, 4): (0.0207, 0.0014, 0.0497, 0.0008, 0.0020, 0.0014, 0.0788, 0.0207),
    (32, 1): (0.0911, 0.0052, 0.2201, 0.0045, 0.0037, 0.0072, 0.3716, 0.0686),
    (32, 2): (0.0401, 0.0019, 0.0974, 0.0014, 0.0027, 0.0015, 0.1456, 0.0492),
    (32, 4): (0.0198, 0.0013, 0.0476, 0.0008, 0.0020, 0.0013, 0.0748, 0.0203),
    (128, 1): (0.0636, 0.0040, 0.1528, 0.0030, 0.0035, 0.0056, 0.2396, 0.0661),
    (128, 2): (0.0419, 0.0018, 0.1020, 0.0011, 0.0027, 0.0015, 0.1489, 0.0552),
    (128, 4): (0.0211, 0.0014, 0.0505, 0.0007, 0.0022, 0.0014, 0.0783, 0.0227),
}
# The from-scratch ablation: the earlier network exactly (no adapter; Adam 1e-4, where 1e-3 collapsed it).
_FROM_SCRATCH = {"encoder.model.base.name": "small-cnn", "encoder.model.adapter_channels": 0,
                 "encoder.train.lr": 0.0001}
_TARGET_LABELS = {"x_cart": "x_cart", "sin_theta": "sin theta", "cos_theta": "cos theta", "x_dot": "x_dot",
                  "theta_dot": "theta_dot"}
PROBE = PaperTable(
    name="probe",
    title="Cartpole state regression (MSE), cartpole-probe",
    label_headers=("Embedding", "Lookback"),
    columns=(MetricColumn("average", "Average"), MetricColumn("position", "Position"),
             MetricColumn("motion", "Motion"))
    + tuple(MetricColumn(f"mse_{k}", _TARGET_LABELS[k]) for k in TARGETS)
    + tuple(MetricColumn(f"r2_{k}", f"R^2 {_TARGET_LABELS[k]}") for k in TARGETS),
    rows=tuple(PaperRow((str(dim), str(lookback)), f"mftcn{lookback}", "cartpole-probe",
                        {"encoder.embedding_dim": dim}, (*paper, *(None,) * len(TARGETS)))
               for (dim, lookback), paper in _PROBE_PAPER.items())
    + (PaperRow(("32", "4, from scratch"), "mftcn4", "cartpole-probe", _FROM_SCRATCH),),
    note="The paper's figures are at paper scale (160,000 train / 20,000 test frames); it gives no R^2. "
         "\"4, from scratch\": mftcn4 on the earlier small CNN trained end to end instead of the frozen base "
         "(the ablation: " + " ".join(f"`--set {k}={v}`" for k, v in _FROM_SCRATCH.items()) + ").",
    varied=(*VARIED, *_FROM_SCRATCH),
)

# --- Table "Results on CartPole Swingup task": cumulative reward over 100 test episodes ------------------
_RETURN_COLUMNS = (MetricColumn("return_mean", "Mean"), MetricColumn("return_std", "Std."))
SWINGUP = PaperTable(
    name="swingup",
    title="Cartpole swing-up, PPO on the frozen embedding: episode return",
    label_headers=("Input to PPO", "Lookback", "Pixels", "Resolution"),
    columns=_RETURN_COLUMNS,
    rows=(
        PaperRow(("Random State", "1", "", ""), "random-state", "swingup", paper=(121.45, 11.98)),
        PaperRow(("True State", "1", "", ""), "true-state", "swingup", paper=(861.41, 3.46)),
        PaperRow(("Pixels (CNN)", "1", "yes", "96x48"), "pixels-cnn", "swingup", paper=(283.82, 42.88)),
        PaperRow(("PVE", "1", "yes", "96x48"), "pve", "swingup", paper=(457.27, 51.16)),
        PaperRow(("mfTCN", "1", "yes", "96x48"), "mftcn1", "swingup", paper=(550.98, 53.40)),
        PaperRow(("mfTCN", "5", "yes", "96x48"), "mftcn5", "swingup", paper=(701.30, 80.14)),
        PaperRow(("mfTCN", "1", "yes", "160x160"), "mftcn1", "swingup-160", paper=(759.33, 77.77)),
        PaperRow(("mfTCN", "5", "yes", "160x160"), "mftcn5", "swingup-160", paper=(787.47, 67.80)),
        PaperRow(("mfTCN (moving)", "1", "yes", "160x160"), "mftcn1", "swingup-moving", paper=(691.77, 85.28)),
        PaperRow(("mfTCN (moving)", "5", "yes", "160x160"), "mftcn5", "swingup-moving", paper=(811.10, 41.80)),
    ),
    note="Mean: mean over seeds of each run's mean test-episode return; Std.: mean over seeds of each run's "
         "std over test episodes (the paper's Std. is over its 100 test episodes).",
    decimals=2,
)

# --- Table "Results on Cheetah Walk task" (the suite's cheetah-run) --------------------------------------
CHEETAH = PaperTable(
    name="cheetah",
    title="Cheetah (encoder trained on expert demonstrations only), PPO on the frozen embedding: episode return",
    label_headers=("Input to PPO",),
    columns=_RETURN_COLUMNS,
    rows=(
        PaperRow(("Random State",), "random-state", "cheetah", paper=(28.31, 3.62)),
        PaperRow(("True State",), "true-state", "cheetah", paper=(390.16, 44.85)),
        PaperRow(("Pixels (CNN)",), "pixels-cnn", "cheetah", paper=(146.14, 29.51)),
        PaperRow(("mfTCN",), "mftcn5", "cheetah", paper=(360.50, 76.52)),
    ),
    note="The paper does not give the lookback of its cheetah mfTCN; its row is set beside our mftcn5.",
    decimals=2,
)

# --- Table "Attributes classification and alignment metrics on the Pouring Dataset" ----------------------
POURING = PaperTable(
    name="pouring",
    title="Pouring: 1-NN attribute classification and alignment errors (%)",
    label_headers=("Model", "Lookback"),
    columns=(MetricColumn("static_error", "Static"), MetricColumn("motion_error", "Motion"),
             MetricColumn("alignment_error", "Alignment")),
    rows=(
        PaperRow(("Random", "1"), "random-state", "pouring", paper=(54.2, None, None)),
        PaperRow(("Inception", "1"), "inception", "pouring", paper=(51.9, None, None)),
        PaperRow(("Shuffle & Learn", "1"), "shuffle-and-learn", "pouring", paper=(27.0, None, None)),
        PaperRow(("TCN", "1"), "tcn", "pouring", paper=(22.2, None, None)),
        PaperRow(("mfTCN^1", "1"), "mftcn1", "pouring", paper=(18.9, 30.2, 16.2)),
        PaperRow(("mfTCN^7", "7"), "mftcn7", "pouring", paper=(17.3, 24.8, 14.3)),
        PaperRow(("mfTCN^13", "13"), "mftcn13", "pouring", paper=(16.8, 18.3, 11.3)),
        PaperRow(("mfTCN^29", "29"), "mftcn29", "pouring", paper=(19.4, 20.9, 8.9)),
    ),
    note="Ours: the simulated pouring dataset. The paper's figures (in brackets) are on the REAL Multiview "
         "Pouring dataset, shown for reference, not as a like-for-like comparison.",
    decimals=1,
)

# --- Table "Attribute-wise classification results on the Pouring Dataset" --------------------------------
_ATTRIBUTE_COLUMNS = (
    ("contact", "contact"), ("tilt_angle", "angle"), ("within_distance", "distance"),
    ("has_liquid", "has liquid"), ("liquid_flowing", "liquid flowing"), ("coming_down", "container down"),
    ("going_up", "container up"), ("reaching", "hand reaching"), ("receding", "hand receding"),
)
_NO_MOTION = (None, None, None, None)
POURING_ATTRIBUTES = PaperTable(
    name="pouring-attributes",
    title="Pouring: attribute-wise 1-NN classification error (%); static, then motion attributes",
    label_headers=("Model", "Lookback"),
    columns=tuple(MetricColumn(f"error_{attr}", label) for attr, label in _ATTRIBUTE_COLUMNS),
    rows=(
        PaperRow(("Random", "1"), "random-state", "pouring", paper=(49.9, 74.5, 48.9, 49.2, 48.4) + _NO_MOTION),
        PaperRow(("Inception", "1"), "inception", "pouring", paper=(47.4, 71.8, 45.2, 48.8, 49.2) + _NO_MOTION),
        PaperRow(("Shuffle & Learn", "1"), "shuffle-and-learn", "pouring",
                 paper=(17.2, 46.3, 17.8, 25.7, 28.0) + _NO_MOTION),
        PaperRow(("TCN", "1"), "tcn", "pouring", paper=(8.0, 35.9, 9.0, 24.7, 35.5) + _NO_MOTION),
        PaperRow(("mfTCN^1", "1"), "mftcn1", "pouring",
                 paper=(7.2, 39.5, 9.5, 27.4, 14.6, 34.5, 30.6, 30.5, 29.6)),
        PaperRow(("mfTCN^7", "7"), "mftcn7", "pouring",
                 paper=(8.2, 39.7, 10.6, 22.1, 10.3, 25.7, 25.6, 25.8, 25.0)),
        PaperRow(("mfTCN^13", "13"), "mftcn13", "pouring",
                 paper=(8.2, 38.7, 9.1, 18.5, 10.2, 22.6, 19.7, 17.2, 17.6)),
        PaperRow(("mfTCN^29", "29"), "mftcn29", "pouring",
                 paper=(8.6, 37.5, 11.2, 16.1, 10.3, 25.4, 20.3, 16.2, 20.7)),
    ),
    note=POURING.note,
    decimals=1,
)

# --- Not in the paper: what limits PPO on an embedding (swing-up at 96x48) -----------------------------
_FRAMES = "task.ppo.frames"
_BUDGETS = {"1 M": 1_000_000, "3 M": 3_000_000}  # the quick and the paper preset's PPO frames
_EVAL = {"1 M": {}, "3 M": {"task.ppo.eval_episodes": 100}}  # 3 M: the paper preset's test episodes
SWINGUP_LIMITS = PaperTable(
    name="swingup-limits",
    title="What limits PPO on an embedding: cartpole swing-up at 96x48, by policy input and PPO budget",
    label_headers=("Input to PPO", "PPO frames"),
    columns=_RETURN_COLUMNS,
    rows=tuple(
        PaperRow((label, budget), encoder, task, {_FRAMES: _BUDGETS[budget], **_EVAL[budget]},
                 paper if budget == "3 M" else None)
        for label, encoder, task, budgets, paper in (
            ("True state", "true-state", "swingup", ("1 M", "3 M"), (861.41, 3.46)),
            ("True state + noise of mfTCN5's probe residual", "true-state-noisy", "swingup", ("1 M", "3 M"), None),
            ("mfTCN5 -> the probe's predicted state", "mftcn5", "swingup-probe-state", ("1 M", "3 M"), None),
            ("mfTCN5 [e_t, e_t - e_t-1]", "mftcn5", "swingup-difference", ("1 M", "3 M"), None),
            ("mfTCN5 e_t", "mftcn5", "swingup", ("1 M", "3 M"), (701.30, 80.14)),
            ("mfTCN1 [e_t, e_t - e_t-1]", "mftcn1", "swingup-difference", ("1 M", "3 M"), None),
            ("mfTCN1 e_t", "mftcn1", "swingup", ("1 M", "3 M"), (550.98, 53.40)),
        )
        for budget in budgets),
    note="Runs of the quick preset (encoders trained on the quick dataset) with PPO's budget as the row says "
         "(`--set task.ppo.frames=3000000 --set task.ppo.eval_episodes=100` for 3 M), and of the paper preset. "
         "The paper's figures (in brackets) are its rows at its budget. Other encoders' swing-up runs are in "
         "the swing-up table.",
    decimals=2,
    varied=(*VARIED, _FRAMES, "task.ppo.eval_episodes"),
    other_runs=False,
)

# --- Not in the paper: what limits PPO on an embedding, by the policy's input alone ------------------------
def _policy_input_table(name: str, title: str, rows: tuple, note: str) -> PaperTable:
    """A table of rows (label, encoder, task, paper figure) that differ only in what the policy sees."""
    return PaperTable(name=name, title=title, label_headers=("Input to PPO",), columns=_RETURN_COLUMNS,
                      rows=tuple(PaperRow((label,), encoder, task, paper=paper)
                                 for label, encoder, task, paper in rows),
                      note=note, decimals=2, other_runs=False)


SWINGUP_160_LIMITS = _policy_input_table(
    "swingup-160-limits",
    "What limits PPO on an embedding: cartpole swing-up at 160x160 (fixed camera), by policy input",
    (("True state", "true-state", "swingup-160", (861.41, 3.46)),
     ("mfTCN1 [e_t, e_t - e_t-1]", "mftcn1", "swingup-160-difference", None),
     ("mfTCN1 e_t", "mftcn1", "swingup-160", (759.33, 77.77)),
     ("mfTCN5 e_t", "mftcn5", "swingup-160", (787.47, 67.80))),
    "The same PPO budget on every row (the preset's); the [e_t, e_t - e_t-1] row shares the e_t row's data set "
    "and encoder fit (same preset and seed), so the rows differ only in the policy's input. Other encoders' runs "
    "are in the swing-up table.")
CHEETAH_LIMITS = _policy_input_table(
    "cheetah-limits",
    "What limits PPO on an embedding: cheetah, by policy input",
    (("True state", "true-state", "cheetah", (390.16, 44.85)),
     ("mfTCN5 [e_t, e_t - e_t-1]", "mftcn5", "cheetah-difference", None),
     ("mfTCN5 e_t", "mftcn5", "cheetah", (360.50, 76.52))),
    "The same PPO budget on every row (3 M frames, at both presets); the [e_t, e_t - e_t-1] row shares the e_t "
    "row's expert, demonstrations and encoder fit (same preset and seed), so the rows differ only in the "
    "policy's input. Other encoders' cheetah runs are in the cheetah table.")

# --- Not in the paper: the encoder's stream of frames at the physics rate and at the agent rate -----------
_PHYSICS, _AGENT = "physics rate (0.01 s)", "agent rate (0.08 s)"
_PROBE_STREAMS = ((_PHYSICS, ""), (_AGENT, "-agent-rate"))  # label, task name suffix: the probe's default
_CONTROL_STREAMS = ((_PHYSICS, "-physics-rate"), (_AGENT, ""))  # and the control tasks' are not the same stream
PROBE_STREAMS = PaperTable(
    name="probe-streams",
    title="Cartpole state regression (MSE, R^2) on the two streams of frames",
    label_headers=("Stream", "Encoder"),
    columns=(MetricColumn("average", "Average"), MetricColumn("motion", "Motion"))
    + tuple(MetricColumn(f"r2_{k}", f"R^2 {_TARGET_LABELS[k]}") for k in TARGETS),
    rows=tuple(PaperRow((stream, encoder), encoder, f"cartpole-probe{suffix}")
               for stream, suffix in _PROBE_STREAMS for encoder in ("lite0-features", "mftcn1", "mftcn5")),
    note="Physics rate: cartpole-probe (a frame every simulator step, the paper's Table 1 data); agent rate: "
         "cartpole-probe-agent-rate (a frame every 8 simulator steps, swing-up's action repeat), the same frame "
         "counts. The targets' variances differ between the streams (theta_dot about 47 against 16 at the "
         "agent rate), so compare the R^2 columns across streams, the MSEs within one.",
    other_runs=False,
)
SWINGUP_STREAMS = PaperTable(
    name="swingup-streams",
    title="Cartpole swing-up at 96x48 by the encoder's stream of frames and the policy's input",
    label_headers=("Stream", "Input to PPO"),
    columns=_RETURN_COLUMNS,
    rows=(PaperRow(("-", "True state"), "true-state", "swingup"),)
    + tuple(PaperRow((stream, f"{encoder} {view}"), encoder, f"swingup{suffix}{variant}")
            for stream, suffix in _CONTROL_STREAMS for encoder in ("mftcn1", "mftcn5")
            for view, variant in (("e_t", ""), ("[e_t, e_t - e_t-1]", "-difference"))),
    note="The same PPO frames on every row (the quick preset: 1 M). Physics rate: swingup-physics-rate[-difference] "
         "(the encoder trained on cartpole-random, clips of consecutive simulator frames, e_t-1 the frame before "
         "inside the action repeat); agent rate, the control tasks' default: swingup and swingup-difference "
         "(trained on cartpole-agent-rate, one frame per agent step, e_t-1 the agent step before).",
    decimals=2,
    other_runs=False,
)

# --- Not in the paper: behaviour cloning on the frozen embedding ------------------------------------------
_DEMONSTRATIONS = "task.bc.demonstrations"
_IMITATE_ROWS = (("True state (BC's upper bound)", "true-state"), ("Random state (the floor)", "random-state"),
                 ("Lite0 features (the frozen base alone)", "lite0-features"), ("PVE", "pve"), ("TCN", "tcn"),
                 ("mfTCN1", "mftcn1"), ("mfTCN5", "mftcn5"))
IMITATE = PaperTable(
    name="imitate",
    title="Behaviour cloning on the frozen embedding from a true-state PPO expert's demonstrations: episode return",
    label_headers=("Domain", "Input to the clone"),
    columns=(*_RETURN_COLUMNS, MetricColumn("fraction_of_expert", "Fraction of expert"),
             MetricColumn("expert_return_mean", "Expert (same initial states)")),
    rows=tuple(PaperRow((domain, label), encoder, task) for domain, task in
               (("swing-up", "imitate-swingup"), ("cheetah", "imitate-cheetah")) for label, encoder in _IMITATE_ROWS),
    note="The expert's row is the last column: each run stores the expert's return on its own test episodes' "
         "initial states. Runs with another number of demonstrations (`--set task.bc.demonstrations=5`) are rows "
         "of their own.",
    decimals=2,
    varied=(*VARIED, _DEMONSTRATIONS),
)

TABLES: dict[str, PaperTable] = {t.name: t for t in (PROBE, SWINGUP, CHEETAH, POURING, POURING_ATTRIBUTES,
                                                     SWINGUP_LIMITS, SWINGUP_160_LIMITS, CHEETAH_LIMITS,
                                                     PROBE_STREAMS, SWINGUP_STREAMS,
                                                     IMITATE)}
