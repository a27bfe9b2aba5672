"""The one progress bar: what it shows, and that it is closed however its block ends."""

import pytest

from mftcn_bench.core import progress


class FakeBar:
    made: list["FakeBar"] = []

    def __init__(self, **kwargs):
        self.kwargs, self.total, self.n, self.postfix, self.closed, self.refreshes = kwargs, None, 0, None, False, 0
        FakeBar.made.append(self)

    def set_postfix(self, postfix, refresh):
        self.postfix = postfix

    def refresh(self):
        self.refreshes += 1

    def close(self):
        self.closed = True


@pytest.fixture
def bars(monkeypatch):
    import tqdm

    FakeBar.made.clear()
    monkeypatch.setattr(tqdm, "tqdm", FakeBar)
    return FakeBar.made


def test_the_bar_shows_done_of_total_with_the_statistics(bars):
    with progress.progress_bar("fit mftcn5", "step") as report:
        report(3, 10, {"loss": 0.123456, "lr": 0.001})
    (bar,) = bars
    assert (bar.n, bar.total, bar.postfix, bar.refreshes) == (3, 10, {"loss": "0.1235", "lr": "0.001"}, 1)
    assert bar.kwargs == {"desc": "fit mftcn5", "unit": "step", "disable": None, "leave": False} and bar.closed


def test_no_progress_disables_it_and_a_failing_block_still_closes_it(bars):
    with pytest.raises(KeyboardInterrupt), progress.progress_bar("ppo swingup", "batch", enabled=False) as report:
        report(1, 2, {})
        raise KeyboardInterrupt
    (bar,) = bars
    assert bar.kwargs["disable"] is True and bar.closed
