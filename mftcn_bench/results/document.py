"""Documents whose tables are generated from run records, so their text cannot drift from the records.

A block

    <!-- generated: report probe --preset quick -->
    ...
    <!-- end generated -->

is replaced by `report` of that table (optionally one preset; `report scorecard` is the scorecard) from the
given store; everything outside
the blocks is prose and stays as written. `mftcn-bench results doc docs/RESULTS.md` fills the blocks from
`results/` (a temporary store imported from the committed records), and a test checks that the committed
document equals its regeneration.
"""

from __future__ import annotations

import re

from mftcn_bench.core.errors import SpecError
from mftcn_bench.results import scorecard
from mftcn_bench.results.report import TABLES, report
from mftcn_bench.results.store import ResultStore

BLOCK = re.compile(r"(<!-- generated: (?P<command>[^>]*?) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S)


def _render(command: str, store: ResultStore) -> str:
    words = command.split()
    tables = [*TABLES, "scorecard"]
    if len(words) not in (2, 4) or words[0] != "report" or words[1] not in tables or (
            len(words) == 4 and words[2] != "--preset"):
        raise SpecError(f"generated block {command!r}: expected `report <table> [--preset <name>]` with a table "
                        f"among {', '.join(tables)}")
    preset = words[3] if len(words) == 4 else None
    if words[1] == "scorecard":
        return scorecard.render(scorecard.build(store.query(), preset or "paper"))
    return report(store, [words[1]], preset)


def fill_generated(text: str, store: ResultStore) -> str:
    """`text` with every generated block rendered afresh from `store`."""
    return BLOCK.sub(lambda m: f"{m.group(1)}{_render(m.group('command'), store)}\n{m.group(4)}", text)
