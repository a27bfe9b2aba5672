"""The web leaderboard, driven in a real browser: Debian's headless Chromium through Playwright."""

from __future__ import annotations

import shutil

import pytest

from mftcn_bench.results.site import paper_figure, write_site
from tests.test_scorecard import records, swingup_runs

CHROMIUM = shutil.which("chromium")


def test_the_page_is_self_contained_and_links_every_entry_to_its_records(tmp_path):
    page = write_site(records(), tmp_path / "site", accept=lambda r: True)
    text = page.read_text()
    assert "http://" not in text and "https://" not in text and "<script src" not in text  # nothing fetched
    assert 'src="data:image/png;base64,' in text  # the performance profiles inline
    linked = {part.split('"')[0] for part in text.split('href="records/')[1:]}
    assert linked and all((tmp_path / "site" / "records" / name).is_file() for name in linked)
    assert paper_figure("mftcn5", "swingup", "return_mean") == 701.30  # the paper's figure beside the row
    assert ">701.3<" in text


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH: `apt-get install chromium` (setup.sh does "
                                             "where it may) to drive the web leaderboard in a browser")
def test_chromium_sorts_a_column_and_filters_by_task_family(tmp_path):
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is a dev dependency")
    from dataclasses import replace

    paper = replace(swingup_runs("mftcn1", [400.0])[0], preset="paper", run_id="paper-run")
    runs = [*records(), *swingup_runs("pve", [200.0, 260.0, 240.0]), paper]
    page_path = write_site(runs, tmp_path / "site", accept=lambda r: True)
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        page.goto(page_path.as_uri())
        board = page.locator('section[data-task="swingup"][data-preset="quick"]')

        def order() -> list[str]:
            return board.locator("tbody tr td.encoder").all_inner_texts()

        assert order() == ["mftcn5", "mftcn1", "pve", "true-state", "random-state"]  # ranked, references after
        column = board.locator("th", has_text="Return (1000 steps) (mean ± std)")
        column.click()
        assert order() == ["random-state", "pve", "mftcn1", "mftcn5", "true-state"]  # ascending
        column.click()
        assert order() == ["true-state", "mftcn5", "mftcn1", "pve", "random-state"]
        page.select_option("#family", "cartpole")
        assert board.is_hidden()
        assert page.locator('section[data-task="cartpole-probe"]').is_visible()
        assert page.locator("section.overall").first.is_visible()  # the overall board spans every family
        page.select_option("#family", "all")
        page.select_option("#preset", "paper")
        assert board.is_hidden() and page.locator('section[data-task="swingup"][data-preset="paper"]').is_visible()
        shot = tmp_path / "leaderboard.png"
        page.select_option("#preset", "all")
        page.screenshot(path=str(shot), full_page=True)
        browser.close()
    assert shot.stat().st_size > 10_000
    print(f"screenshot: {shot}")
