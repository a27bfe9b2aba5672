import multiprocessing

from mftcn_bench.store import ResultStore, RunRecord


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
