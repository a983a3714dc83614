"""``mocapskel batch`` and ``mocapskel compare``: many takes locally and on a Dask cluster,
a broken take among good ones, re-runs, Ctrl-C, and subject identification.

Driven through click's CliRunner; every output is reopened and checked.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel.batch import local_runner, worker
from mocapskel.batch.clustering import choose_clusters
from mocapskel.batch.inputs import collect_inputs, take_names
from mocapskel.batch.proportions import proportion_distance
from mocapskel.batch.summary import SUMMARY_COLUMNS, read_summary
from mocapskel.cli.main import cli
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.markers import write_markers
from mocapskel.synth.presets import Recipe, make

REPO = Path(__file__).resolve().parents[1]


def run(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    return r.exit_code, r.stdout, r.stderr


def _write_take(path: Path, recipe: Recipe) -> None:
    take = make(recipe)
    write_markers(path, replace(take.markers, source=path.name))


def _rows(outdir: Path) -> dict[str, dict[str, str]]:
    return {r["take"]: r for r in read_summary(outdir / "summary.csv")}


# --------------------------------------------------------------------------- a small batch with a broken take


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """Three quick takes and a file of random bytes named like a C3D, batched with 2 local workers."""
    d = tmp_path_factory.mktemp("small")
    takes = d / "takes"
    takes.mkdir()
    _write_take(takes / "link_a.trc", Recipe(kind="linkage", frames=600, noise_mm=0.5, seed=1))
    _write_take(takes / "link_b.c3d", Recipe(kind="linkage", frames=500, noise_mm=0.5, seed=2))
    _write_take(takes / "chain.trc", Recipe(kind="chain", counts=(4, 3, 3), frames=300, seed=3))
    (takes / "x.c3d").write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    out = d / "out"
    code, _, err = run("batch", takes, "-o", out, "--jobs", 2, "--no-cache")
    return takes, out, code, err


def test_broken_take_fails_alone(small):
    takes, out, code, err = small
    assert code == 1, err  # 1: some takes failed
    assert "1 of 4 takes failed" in err and "summary.csv" in err
    for i, name in enumerate(("chain.trc", "link_a.trc", "link_b.c3d", "x.c3d"), 1):
        assert any(line.startswith(f"[{j}/4] {name} ") for j in range(1, 5) for line in err.splitlines()), err
    with open(out / "summary.csv", encoding="utf-8") as f:
        assert f.readline().strip() == ",".join(SUMMARY_COLUMNS)
    rows = _rows(out)
    assert list(rows) == ["chain", "link_a", "link_b", "x"]  # input order, whatever order they finished in
    x = rows["x"]
    assert x["status"] == "failed" and x["exit_code"] == "3"
    assert "x.c3d" in x["error"] and "\n" not in x["error"]
    assert not (out / "x.bvh").exists() and not (out / "x.json").exists()
    expect = {"chain": (300, 10, 3), "link_a": (600, 9, 3), "link_b": (500, 9, 3)}
    for name, (frames, markers, segments) in expect.items():
        r = rows[name]
        assert r["status"] == "ok" and r["exit_code"] == "0" and r["error"] == ""
        assert (int(r["frames"]), int(r["markers"]), int(r["segments"])) == (frames, markers, segments)
        assert float(r["ik_rms_mm"]) < 2.0 and float(r["seconds"]) > 0
        skel, root_pos, _, _ = read_bvh(out / f"{name}.bvh")
        assert root_pos.shape[0] == frames and len(skel.names) == segments
        rep = json.loads((out / f"{name}.json").read_text())
        assert rep["input"]["frames"] == frames and len(rep["batch"]["options_hash"]) == 64
        lengths = dict(kv.split("=") for kv in r["bone_lengths_mm"].split(";"))
        assert {b["segment"]: round(b["length_mm"], 2) for b in rep["bones"]} == {k: float(v) for k, v in lengths.items()}
    # every fitted take has a subject, the failed one none
    assert all(rows[name]["subject"].startswith("S") for name in expect)
    assert rows["x"]["subject"] == ""
    assert not list(out.glob("*.part")) and not list(out.glob(".*"))


def test_rerun_skips_finished_takes_unless_options_change_or_force(small, tmp_path):
    takes, out0, _, _ = small
    out = tmp_path / "out"
    code, _, _ = run("batch", takes / "link_a.trc", takes / "chain.trc", "-o", out, "--jobs", 1, "--no-cache")
    assert code == 0
    stamp = {p.name: p.stat().st_mtime_ns for p in out.glob("*.[bj]*")}
    code, _, err = run("batch", takes / "link_a.trc", takes / "chain.trc", "-o", out, "--jobs", 1, "--no-cache")
    assert code == 0, err
    assert "skipped (up to date)" in err
    assert {r["status"] for r in _rows(out).values()} == {"skipped"}
    assert stamp == {p.name: p.stat().st_mtime_ns for p in out.glob("*.[bj]*")}
    a, b = _rows(out), _rows(out0)
    for name in ("link_a", "chain"):
        for col in ("frames", "markers", "segments", "bone_lengths_mm", "ik_rms_mm"):
            assert a[name][col] == b[name][col]
    # another option: fitted again
    code, _, err = run("batch", takes / "link_a.trc", takes / "chain.trc", "-o", out, "--jobs", 1, "--no-cache", "--units", "mm")
    assert code == 0 and {r["status"] for r in _rows(out).values()} == {"ok"}
    skel, *_ = read_bvh(out / "link_a.bvh")
    skel0, *_ = read_bvh(out0 / "link_a.bvh")
    assert np.allclose(skel.offset, 10 * skel0.offset, atol=1e-5)
    # the same again: skipped; with --force: fitted
    code, _, _ = run("batch", takes / "link_a.trc", "-o", out, "--jobs", 1, "--no-cache", "--units", "mm")
    assert _rows(out)["link_a"]["status"] == "skipped"
    code, _, _ = run("batch", takes / "link_a.trc", "-o", out, "--jobs", 1, "--no-cache", "--units", "mm", "--force")
    assert code == 0 and _rows(out)["link_a"]["status"] == "ok"
    # a touched input is fitted again
    st = (takes / "link_a.trc").stat()
    later = time.time_ns() + 5_000_000_000
    os.utime(takes / "link_a.trc", ns=(later, later))
    try:
        code, _, _ = run("batch", takes / "link_a.trc", "-o", out, "--jobs", 1, "--no-cache", "--units", "mm")
        assert _rows(out)["link_a"]["status"] == "ok"
    finally:
        os.utime(takes / "link_a.trc", ns=(st.st_atime_ns, st.st_mtime_ns))


def test_interrupted_batch_leaves_no_partial_output(small, tmp_path, monkeypatch):
    takes, _, _, _ = small
    real = worker.fit_take
    calls = []

    def fit_then_interrupt(task):
        calls.append(task.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(task)

    monkeypatch.setattr(local_runner, "fit_take", fit_then_interrupt)
    out = tmp_path / "out"
    code, _, err = run("batch", takes, "-o", out, "--jobs", 1, "--no-cache")
    assert code == 130 and "interrupted" in err
    assert calls == ["chain", "link_a"]
    assert sorted(p.name for p in out.iterdir()) == ["chain.bvh", "chain.json"]  # no summary, no temporary file
    read_bvh(out / "chain.bvh")


@pytest.mark.parametrize("stop, code, word", [("Interrupted", 130, "interrupted"), ("Terminated", 143, "terminated")])
def test_a_signal_that_python_wrapped_in_another_error_stops_the_batch(small, tmp_path, monkeypatch, stop, code, word):
    """A Ctrl-C or SIGTERM that Python 3.11 wrapped in a RuntimeError (raised while a dataclass was created
    by a lazy import) stops the batch with its code, as it would unwrapped: it is not a failed take. An
    unrelated RuntimeError is still one failed take, and the batch goes on."""
    from mocapskel import pipeline
    from mocapskel.cli import main as cli_main

    takes, _, _, _ = small
    real = pipeline.fit
    calls = []

    def fit_then_wrapped_signal(path, *args, **kwargs):
        calls.append(Path(path).name)
        if len(calls) == 2:
            try:
                raise getattr(cli_main, stop)()
            except BaseException as e:
                raise RuntimeError("Error calling __set_name__ on 'Field' instance 'computed' in 'RawTake'") from e
        return real(path, *args, **kwargs)

    monkeypatch.setattr(pipeline, "fit", fit_then_wrapped_signal)
    out = tmp_path / "out"
    rc, _, err = run("batch", takes, "-o", out, "--jobs", 1, "--no-cache")
    assert rc == code and word in err and "unexpected" not in err
    assert calls == ["chain.trc", "link_a.trc"]
    assert sorted(p.name for p in out.iterdir()) == ["chain.bvh", "chain.json"]  # no summary, no temporary file

    def fit_then_bug(path, *args, **kwargs):
        if Path(path).name == "link_a.trc":
            raise RuntimeError("something else")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(pipeline, "fit", fit_then_bug)
    out2 = tmp_path / "out2"
    rc, _, _ = run("batch", takes, "-o", out2, "--jobs", 1, "--no-cache")
    rows = _rows(out2)
    assert rows["link_a"]["status"] == "failed" and "unexpected RuntimeError: something else" in rows["link_a"]["error"]
    assert rows["chain"]["status"] == "ok"


def test_inputs_files_folders_globs(small, tmp_path):
    takes, _, _, _ = small
    assert [p.name for p in collect_inputs([takes])] == ["chain.trc", "link_a.trc", "link_b.c3d", "x.c3d"]
    assert [p.name for p in collect_inputs([str(takes / "*.trc"), takes / "chain.trc"])] == ["chain.trc", "link_a.trc"]
    assert take_names([Path("a/run.c3d"), Path("b/run.trc"), Path("c/RUN.c3d"), Path("walk.c3d")]) == [
        "run_c3d", "run_trc", "RUN_c3d_2", "walk"]
    code, _, err = run("batch", tmp_path / "missing.c3d", "-o", tmp_path / "out")
    assert code == 2 and "missing.c3d" in err
    code, _, err = run("batch", str(tmp_path / "*.c3d"), "-o", tmp_path / "out")
    assert code == 2 and "matches no .c3d or .trc" in err
    (tmp_path / "file").write_text("")
    code, _, err = run("batch", takes / "chain.trc", "-o", tmp_path / "file")
    assert code == 2


def test_scheduler_without_dask_is_a_usage_error(small, tmp_path, monkeypatch):
    takes, _, _, _ = small
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed → ImportError
    code, _, err = run("batch", takes, "-o", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:8786")
    assert code == 2
    assert "install mocapskel[dask]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- a real Dask cluster


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(pred, timeout: float, what: str, logs: list[Path]) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            tail = "\n".join(p.read_text(errors="replace")[-2000:] for p in logs if p.exists())
            raise RuntimeError(f"timed out waiting for {what}\n{tail}")
        time.sleep(0.2)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


@pytest.fixture(scope="module")
def dask_scheduler(tmp_path_factory):
    """A `dask scheduler` and two `dask worker`s on 127.0.0.1 (subprocesses, stopped at teardown)."""
    pytest.importorskip("distributed")
    d = tmp_path_factory.mktemp("dask")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    sched_log = d / "scheduler.log"
    workers: list[subprocess.Popen] = []
    scheduler: list[subprocess.Popen] = []
    logs = [sched_log]
    try:
        for _ in range(3):  # the free port may be taken before the scheduler binds it (tests run side by side)
            port = _free_port()
            address = f"tcp://127.0.0.1:{port}"
            with open(sched_log, "wb") as f:
                scheduler.append(subprocess.Popen(
                    [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                     "--no-dashboard"], cwd=d, env=env, stdout=f, stderr=subprocess.STDOUT))
            _wait_for(lambda: "Scheduler at" in sched_log.read_text(errors="replace") or scheduler[-1].poll() is not None,
                      180, "the scheduler", logs)
            if scheduler[-1].poll() is None:
                break
        for i in range(2):
            log = d / f"worker{i}.log"
            logs.append(log)
            with open(log, "wb") as f:
                workers.append(subprocess.Popen(
                    [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--no-nanny",
                     "--no-dashboard", "--host", "127.0.0.1", "--name", f"w{i}", "--local-directory", str(d)],
                    cwd=d, env=env, stdout=f, stderr=subprocess.STDOUT))
        _wait_for(lambda: sched_log.read_text(errors="replace").count("Register worker") >= 2, 180, "2 workers", logs)
        yield address
    finally:
        _stop(workers)  # the workers first, while the scheduler can still say goodbye
        _stop(scheduler)


def test_dask_cluster_gives_the_same_outputs_as_local_workers(small, dask_scheduler, tmp_path):
    takes, local, _, _ = small
    out = tmp_path / "dask"
    code, _, err = run("batch", takes, "-o", out, "--scheduler", dask_scheduler, "--no-cache")
    assert code == 1, err  # x.c3d fails there too
    a, b = _rows(local), _rows(out)
    assert list(a) == list(b)
    for name in a:
        for col in SUMMARY_COLUMNS:
            if col != "seconds":
                assert a[name][col] == b[name][col], (name, col)
        if a[name]["status"] == "ok":
            assert (out / f"{name}.bvh").read_bytes() == (local / f"{name}.bvh").read_bytes()
            ra, rb = (json.loads((p / f"{name}.json").read_text()) for p in (local, out))
            assert ra["bones"] == rb["bones"] and ra["batch"] == rb["batch"]


# --------------------------------------------------------------------------- subjects

#: Three generated subjects: their own proportions (each body part varies by up to ±3 %),
#: sizes 5 % apart; three takes each. (Subject seeds 1, 2, 4: typical differences of
#: 1.5–2.2 % in proportion; two subjects within ~0.5 % of each other cannot be told apart.)
SUBJECTS = ((1, 1.0), (2, 1.05), (4, 0.95))


@pytest.fixture(scope="module")
def people(tmp_path_factory):
    d = tmp_path_factory.mktemp("people")
    takes = d / "takes"
    takes.mkdir()
    for k, (subject_seed, scale) in enumerate(SUBJECTS):
        for t in range(3):
            _write_take(takes / f"p{k}_take{t}.c3d", Recipe(kind="human", seed=100 * k + t, frames=1200, noise_mm=0.5,
                                                            scale=scale, subject_seed=subject_seed))
    out = d / "out"
    code, _, err = run("batch", takes, "-o", out, "--jobs", 2, "--no-cache")
    assert code == 0, err
    return takes, out


def test_subjects_of_generated_takes_are_identified(people):
    takes, out = people
    rows = _rows(out)
    assert len(rows) == 9 and all(r["status"] == "ok" for r in rows.values())
    by_person = {k: {rows[f"p{k}_take{t}"]["subject"] for t in range(3)} for k in range(3)}
    assert all(len(s) == 1 for s in by_person.values()), by_person
    assert len(set.union(*by_person.values())) == 3, by_person
    # the count given: the same grouping; fewer subjects than there are: two people merged
    code, _, err = run("batch", takes, "-o", out, "--no-cache", "--subjects", 3)
    assert code == 0 and "skipped (up to date)" in err
    assert {k: r["subject"] for k, r in _rows(out).items()} == {k: r["subject"] for k, r in rows.items()}
    code, _, _ = run("batch", takes, "-o", out, "--no-cache", "--subjects", 2)
    assert len({r["subject"] for r in _rows(out).values()}) == 2


def test_compare_says_same_subject_or_not(people, tmp_path):
    _, out = people
    code, text, _ = run("compare", out / "p0_take0.json", out / "p0_take2.json")
    assert code == 0
    assert "bones matched by marker labels" in text
    assert text.strip().splitlines()[-1] == "same subject: likely"
    lines = {ln.split()[0]: ln for ln in text.splitlines() if ln[:4] in ("LTHI", "LHND", "TRSO")}
    assert "end site, not compared" in lines["LHND"] and "no length" in lines["TRSO"]
    assert "%" in text and "proportion distance" in text
    code, text, _ = run("compare", out / "p0_take0.json", out / "p1_take1.json")
    assert code == 0 and text.strip().splitlines()[-1] == "same subject: unlikely"
    # without marker labels, and with other names: matched by the tree (left/right limbs paired by proportion)
    for name in ("p0_take1", "p2_take1"):
        rep = json.loads((out / f"{name}.json").read_text())
        rep.pop("segments")
        rename = {b["segment"]: f"s{i:02d}" for i, b in enumerate(rep["bones"])}
        for b in rep["bones"]:
            b["segment"], b["parent"] = rename[b["segment"]], rename.get(b["parent"])
        (tmp_path / f"{name}.json").write_text(json.dumps(rep))
    for other, verdict in (("p0_take1", "likely"), ("p2_take1", "unlikely")):
        code, text, _ = run("compare", out / "p0_take0.json", tmp_path / f"{other}.json")
        assert code == 0 and "bones matched by tree structure" in text
        assert text.strip().splitlines()[-1] == f"same subject: {verdict}"
    # not a report
    (tmp_path / "bad.json").write_text("{}")
    code, _, err = run("compare", out / "p0_take0.json", tmp_path / "bad.json")
    assert code == 3 and "bad.json" in err


def test_compare_different_topologies(small, people):
    code, text, _ = run("compare", small[1] / "chain.json", people[1] / "p0_take0.json")
    assert code == 0 and "different topologies" in text
    assert text.strip().splitlines()[-1].startswith("same subject: unlikely")


def test_choose_clusters_cuts_at_the_widest_gap():
    # three tight groups: spread ~0.3 %, separation ~1.5 %
    assert choose_clusters(np.array([0.1, 0.2, 0.25, 0.3, 0.3, 0.3, 1.4, 1.9])) == (3, "gap")
    # one subject: nothing above the threshold
    assert choose_clusters(np.array([0.1, 0.15, 0.3, 0.35])) == (None, "threshold")
    # every take its own subject
    assert choose_clusters(np.array([1.5, 2.0, 2.5])) == (4, "gap")


def test_proportion_distance_ignores_size_and_one_bad_bone():
    L = np.array([300.0, 250.0, 440.0, 420.0, 180.0, 300.0])
    d, r, worst = proportion_distance(L, 1.05 * L)
    assert d == pytest.approx(0.0, abs=1e-9) and worst >= 0
    bad = L.copy()
    bad[3] *= 0.9
    d, r, worst = proportion_distance(L, bad)
    assert worst == 3 and d == pytest.approx(0.0, abs=1e-9) and r[3] == pytest.approx(-0.1 / 0.95)
    d_all, _, _ = proportion_distance(L, bad, trim=False)
    assert d_all > 2.0
