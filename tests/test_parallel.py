"""Tasks shared out between threads and forked processes: the same results as one after the other."""
from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from mocapskel.solvers import parallel
from mocapskel.solvers.parallel import Shares, n_threads, run_ahead, run_blocks, run_forked

PARENT = os.getpid()
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="run_forked forks on Linux only")


def _work(x: int) -> tuple[int, float, int, int]:
    v = np.linalg.norm(np.random.default_rng(x).normal(size=(50, 50)) @ np.ones(50))
    return x, float(v), os.getpid(), n_threads()


def test_run_forked_gives_the_results_in_order(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "3")
    items = list(range(7))
    got = run_forked(_work, items)
    want = [_work(x) for x in items]
    assert [g[:2] for g in got] == [w[:2] for w in want]
    assert parallel._FORCED is None  # left as found


@linux_only
def test_run_forked_runs_in_other_processes_each_on_one_thread(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    got = run_forked(_work, range(4))
    pids = {g[2] for g in got}
    assert PARENT not in pids and len(pids) == 4  # a child for every item, this process hands them out
    assert all(g[3] == 1 for g in got)  # inside a task, run_blocks uses one thread
    assert n_threads() == 2


def test_run_forked_on_one_core_stays_in_this_process(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "1")
    assert {g[2] for g in run_forked(_work, range(3))} == {PARENT}


def _fails_on_two(x: int) -> int:
    if x == 2:
        raise ValueError(f"bad item {x}")
    return x


def test_run_forked_raises_a_child_error_here(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    with pytest.raises(ValueError, match="bad item 2"):
        run_forked(_fails_on_two, range(4))
    assert parallel._FORCED is None


def _dies_in_a_child(x: int) -> int:
    if os.getpid() != PARENT:
        os._exit(3)  # killed before it could answer
    return 10 * x


@linux_only
def test_run_forked_redoes_here_what_a_dead_child_did_not_send(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    assert run_forked(_dies_in_a_child, range(4)) == [0, 10, 20, 30]


def _unpicklable(x: int):
    return (x, (lambda: x) if os.getpid() != PARENT else None)


@linux_only
def test_run_forked_redoes_here_a_result_that_does_not_pickle(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    assert [g[0] for g in run_forked(_unpicklable, range(3))] == [0, 1, 2]


def test_run_blocks_and_run_forked_agree(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    assert [g[:2] for g in run_blocks(_work, range(5))] == [g[:2] for g in run_forked(_work, range(5))]


def test_a_fit_is_the_same_on_one_core_and_on_several(monkeypatch, tmp_path) -> None:
    """The rigid stage refines its two starts in forked processes and the topology costs its pairs in
    shares: the skeleton and every pose are the same, bit for bit, as one process alone gives."""
    from mocapskel import pipeline
    from mocapskel.synth.presets import active_rom, make

    take = make(active_rom(2, frames=1200, markers_per_segment=2))
    out = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("MOCAPSKEL_THREADS", threads)
        res = pipeline.fit(take.markers, pipeline.make_params())
        assert res.motion.skeleton.joints.alt_centres is not None  # two starts were refined
        out[threads] = res.motion
    one, two = out["1"], out["2"]
    np.testing.assert_array_equal(one.skeleton.origin, two.skeleton.origin)
    np.testing.assert_array_equal(one.skeleton.marker_local, two.skeleton.marker_local)
    np.testing.assert_array_equal(one.skeleton.joints.topology.pair_cost, two.skeleton.joints.topology.pair_cost)
    np.testing.assert_array_equal(one.rot, two.rot)
    np.testing.assert_array_equal(one.root_pos, two.root_pos)


@pytest.mark.parametrize("threads", ["1", "2", "3"])
def test_run_ahead_yields_in_order_with_few_results_held(monkeypatch, threads) -> None:
    import threading

    monkeypatch.setenv("MOCAPSKEL_THREADS", threads)
    started: list[int] = []
    lock = threading.Lock()

    def fn(x: int) -> int:
        with lock:
            started.append(x)
        return x * x

    got = []
    for i, y in enumerate(run_ahead(fn, range(25), ahead=3)):
        got.append(y)
        assert len(started) <= i + 1 + 3  # never more than `ahead` items beyond those taken
    assert got == [x * x for x in range(25)]
    assert sorted(started) == list(range(25))


def test_long_take_paths_are_the_same_on_one_core_and_on_several(monkeypatch) -> None:
    """Clean's rigid jump test, its jump search and the BVH writer work through a long take in blocks on
    threads, and the fit checks its output beside the export: with blocks made small so that a short take
    has many, the cleaned markers, the BVH text and the checks are the same, bit for bit, on one thread
    and on two."""
    from mocapskel import pipeline
    from mocapskel.io import bvh as bvh_io
    from mocapskel.stages import clean
    from mocapskel.synth.presets import active_rom, make

    take = make(active_rom(4, frames=1500, jumps=12))
    monkeypatch.setattr(clean, "_RIGID_BLOCK", 256)
    monkeypatch.setattr(clean, "_WINDOW_CHUNK", 3000)
    monkeypatch.setattr(clean, "_BLOCK_SAMPLES", 4096)
    monkeypatch.setattr(bvh_io, "_BLOCK_FRAMES", 64)
    monkeypatch.setattr(bvh_io, "_CHECK_FRAMES", 128)
    out = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("MOCAPSKEL_THREADS", threads)
        cleaned = clean.run(take.markers)
        res = pipeline.fit(take.markers, pipeline.make_params())
        b = res.bvh
        out[threads] = (cleaned, bvh_io.bvh_text(b.skeleton, b.root_pos, b.local_rot, b.frame_time),
                        res.report["checks"], res.report["warnings"])
    (c1, t1, k1, w1), (c2, t2, k2, w2) = out["1"], out["2"]
    assert c1.info["clean"]["jump_samples"] > 0  # the rigid test had jumps to judge
    np.testing.assert_array_equal(c1.points, c2.points)
    assert c1.info == c2.info
    assert t1 == t2
    assert k1 == k2 and w1 == w2


def _keeper():
    """An item's process keeps the item's state between calls: ("set", v) stores v, ("add", v) adds v
    to what is stored and answers it, with the process and its thread count."""
    store: dict[int, float] = {}

    def fn(j: int, msg: tuple):
        kind, v = msg
        if kind == "fail" and j == v:
            raise ValueError(f"bad item {j}")
        if kind == "die" and j == v and os.getpid() != PARENT:
            os._exit(3)
        store[j] = (store[j] + v) if kind == "add" else v
        return j, store[j], os.getpid(), n_threads()

    return fn


def _children() -> set[int]:
    """This process's children, running or not yet reaped (Linux: every thread's ``children`` list)."""
    out: set[int] = set()
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/children") as f:
                out.update(int(x) for x in f.read().split())
        except FileNotFoundError:  # a thread that ended meanwhile
            pass
    return out


def _no_children_left(before: set[int]) -> bool:
    """No child of this process is left, running or not yet reaped, but those it had ``before`` (another
    test's, in the same process, are not this one's to judge)."""
    return not (_children() - before)


@linux_only
def test_shares_keep_each_items_state_in_its_own_process(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    before = _children()
    with Shares(_keeper(), 5) as sh:
        first = sh.call([("set", float(10 * j)) for j in range(5)])
        second = sh.call([("add", 1.5)] * 5)
    assert [g[:2] for g in first] == [(j, 10.0 * j) for j in range(5)]
    assert [g[:2] for g in second] == [(j, 10.0 * j + 1.5) for j in range(5)]
    # items 0, 2, 4 here, 1 and 3 in one child, on one thread; the same process on both calls
    assert [g[2] == PARENT for g in second] == [True, False, True, False, True]
    assert second[1][2] == second[3][2] == first[1][2] != PARENT
    assert second[1][3] == 1
    assert parallel._FORCED is None and _no_children_left(before)


def test_shares_on_one_core_stay_in_this_process(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "1")
    with Shares(_keeper(), 3) as sh:
        sh.call([("set", 1.0)] * 3)
        got = sh.call([("add", 2.0)] * 3)
    assert [g[1] for g in got] == [3.0, 3.0, 3.0] and {g[2] for g in got} == {PARENT}


@linux_only
def test_shares_raise_a_childs_error_here_and_end_the_children(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    before = _children()
    with pytest.raises(ValueError, match="bad item 3"):
        with Shares(_keeper(), 4) as sh:
            sh.call([("set", 0.0)] * 4)
            sh.call([("fail", 3)] * 4)
    assert _no_children_left(before)


@linux_only
def test_shares_say_so_when_a_child_is_lost(monkeypatch) -> None:
    monkeypatch.setenv("MOCAPSKEL_THREADS", "2")
    before = _children()
    with pytest.raises(RuntimeError, match="ended unexpectedly"):
        with Shares(_keeper(), 2) as sh:
            sh.call([("die", 1)] * 2)
    assert _no_children_left(before)


def _blas_threads() -> int:
    from threadpoolctl import threadpool_info

    return max((int(i["num_threads"]) for i in threadpool_info() if i.get("user_api") == "blas"), default=1)


def test_the_pipeline_runs_with_one_blas_thread_where_numpy_came_first(monkeypatch) -> None:
    """numpy is imported before mocapskel here (as in most users' scripts), so the package's
    variables came too late: the pipeline's entry points limit BLAS themselves, and give the
    previous count back after, unless the user chose one."""
    import mocapskel
    from mocapskel import pipeline
    from mocapskel.synth.presets import active_rom, make
    from threadpoolctl import threadpool_limits

    seen: list[int] = []
    stage = pipeline.stage_module("segment")
    real = stage.run
    monkeypatch.setattr(stage, "run", lambda *a, **k: (seen.append(_blas_threads()), real(*a, **k))[1])
    take = make(active_rom(1, frames=300))
    monkeypatch.setattr(mocapskel, "BLAS_THREADS_CHOSEN", False)
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        pipeline.run_until(take.markers, "segment", pipeline.make_params())
        after = _blas_threads()
        monkeypatch.setattr(mocapskel, "BLAS_THREADS_CHOSEN", True)
        pipeline.run_until(take.markers, "segment", pipeline.make_params())
    assert seen[0] == 1 and after == before
    if before > 1:  # a BLAS that honours the limit of 2: the user's choice stands
        assert seen[1] == before


def test_blas_variables_set_by_mocapskel_are_not_taken_for_the_users_choice(tmp_path) -> None:
    """A process started from one that imported mocapskel (a test worker, a batch worker) sees the
    variables mocapskel set; only variables the user set count as a choice."""
    import subprocess

    code = "import mocapskel, os; print(mocapskel.BLAS_THREADS_CHOSEN, os.environ['OPENBLAS_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                             "MKL_NUM_THREADS", "MOCAPSKEL_BLAS_DEFAULT")}
    run = lambda e: subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True,  # noqa: E731
                                   check=True).stdout.split()
    assert run(env) == ["False", "1"]  # nothing set: mocapskel's default
    assert run({**env, "OPENBLAS_NUM_THREADS": "3"}) == ["True", "3"]  # the user's
    inherited = {**env, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                 "MOCAPSKEL_BLAS_DEFAULT": "1"}
    assert run(inherited) == ["False", "1"]  # what a parent's mocapskel set
