import multiprocessing

from mftcn_bench.results.store import ResultStore, RunRecord


def record(run_id, encoder="mftcn4", metric=1.0, preset="quick"):
    return RunRecord(run_id, encoder, "cartpole-probe", preset, 0, "d1", {"a": 1}, {"torch": "x"},
                     {"average": metric}, {"total_s": 1.0}, "/tmp/x")


def test_put_get_query_replace(tmp_path):
    store = ResultStore(tmp_path / "r.sqlite")
    store.put(record("a"))
    store.put(record("b", encoder="mftcn1", preset="smoke"))
    assert store.get("a").metrics == {"average": 1.0} and store.get("a").config == {"a": 1}
    assert store.get("missing") is None
    assert [r.run_id for r in store.query(task="cartpole-probe", preset="smoke")] == ["b"]
    store.put(record("a", metric=2.0))
    assert store.get("a").metrics["average"] == 2.0 and len(store.query()) == 2
    assert store.integrity_ok()


def _writer(path, worker):
    store = ResultStore(path, busy_timeout_s=30)
    for i in range(25):
        store.put(record(f"{worker}-{i}", metric=float(i)))


def test_four_concurrent_writers_lose_nothing(tmp_path):
    path = tmp_path / "r.sqlite"
    ResultStore(path)
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_writer, args=(path, w)) for w in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    store = ResultStore(path)
    assert len(store.query()) == 100 and store.integrity_ok()


def test_curves_round_trip_and_old_store_gains_the_column(tmp_path):
    import sqlite3

    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as conn:  # the schema before curves were stored
        conn.execute("CREATE TABLE runs (run_id TEXT PRIMARY KEY, encoder TEXT NOT NULL, task TEXT NOT NULL, "
                     "preset TEXT NOT NULL, seed INTEGER NOT NULL, dataset_id TEXT, config TEXT NOT NULL, "
                     "versions TEXT NOT NULL, metrics TEXT NOT NULL, timings TEXT NOT NULL, artifacts TEXT, "
                     "created_at TEXT NOT NULL)")
        conn.execute("INSERT INTO runs VALUES ('old','e','t','quick',0,'d','{}','{}','{}','{}',NULL,'2026')")
    store = ResultStore(path)
    assert store.get("old").curves == {}
    curves = {"train": {"frames": [0.0, 10.0], "return": [1.5, 2.5]}}
    rec = record("new")
    store.put(RunRecord(**{**rec.__dict__, "curves": curves}))
    assert store.get("new").curves == curves and store.integrity_ok()
