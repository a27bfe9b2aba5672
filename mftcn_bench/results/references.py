"""Which encoders a board or the scorecard lists apart, as references: those that read the true state
(`encoders.privileged`) and the scorecard's floor and ceiling (`reports/scorecard.toml`), which set its scale
rather than compete on it. Everything else is ranked as a pixel encoder.
"""

from __future__ import annotations

from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError
from mftcn_bench.encoders.privileged import declared_inputs, is_reference
from mftcn_bench.results.intervals import scorecard_spec
from mftcn_bench.results.store import RunRecord


def privileged_of(record: RunRecord) -> tuple[str, ...]:
    """The privileged inputs the run's encoder declared: as recorded, or (a record made before runs recorded
    them) as its class declares them today; () for an encoder not installed here."""
    recorded = record.config.get("privileged")
    if isinstance(recorded, list):
        return tuple(recorded)
    try:
        return declared_inputs(registry.get("encoders", record.encoder).load())
    except BenchError:
        return ()


def anchors() -> tuple[str, str]:
    """(floor, ceiling): the encoders whose runs score 0 and 1 on the scorecard."""
    spec = scorecard_spec()
    return str(spec["floor"]), str(spec["ceiling"])


def reference_role(record: RunRecord) -> str | None:
    """Why the run's encoder is a reference ('reads: state', 'floor'), or None for a pixel encoder."""
    floor, ceiling = anchors()
    privileged = privileged_of(record)
    if is_reference(privileged):
        return "reads: " + ", ".join(privileged)
    if record.encoder == floor:
        return "floor (random features)"
    if record.encoder == ceiling:
        return "ceiling"
    return None
