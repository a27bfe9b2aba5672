import multiprocessing
import time

from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock


def _hold(lock, log, name):
    with exclusive_lock(lock):
        with open(log, "a") as handle:
            handle.write(f"{name}+")
        time.sleep(0.3)
        with open(log, "a") as handle:
            handle.write(f"{name}-")


def test_lock_serialises_processes(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_hold, args=(tmp_path / "x.lock", tmp_path / "log", n)) for n in "ab"]
    for p in procs:
        p.start()
    for p in procs:
        p.join(30)
    text = (tmp_path / "log").read_text()
    assert text in ("a+a-b+b-", "b+b-a+a-")


def test_atomic_write_leaves_no_temporary_file(tmp_path):
    atomic_write_bytes(tmp_path / "f", b"one")
    atomic_write_bytes(tmp_path / "f", b"two")
    assert (tmp_path / "f").read_bytes() == b"two" and [p.name for p in tmp_path.iterdir()] == ["f"]
