"""`volpuzzle batch` on a real dask.distributed LocalCluster: each folder is the one `build` writes, a bad spec is
one error line while the others go on, a summary table and the exit status at the end."""

import json

import pytest
from click.testing import CliRunner
from helpers_build import write_spec

from volpuzzle.cli import cli
from volpuzzle.pipeline import Progress, build


def _small(name, seed):
    return {"name": name, "model": {"builtin": {"type": "quarter-torus", "major_radius": 50, "minor_radius": 20}},
            "grid": [2, 1, 1], "randomize": {"seed": seed, "amplitude": 0.2, "control_points": 4},
            "output": {"tolerance": 0.5, "labels": False}}


def _report_without_times(path):
    """report.json less what a run measures (its times) and where it was written."""
    report = json.loads(path.read_text(encoding="utf-8"))
    del report["timings_s"], report["checks"]["overlap_time_s"], report["spec"]["output"]["directory"]
    return report


def _report_md_without_times(path):
    lines = path.read_text(encoding="utf-8").splitlines()
    start = lines.index(next(line for line in lines if line.lower().startswith("## tim")))
    stop = next((k for k in range(start + 1, len(lines)) if lines[k].startswith("## ")), len(lines))
    return lines[:start] + lines[stop:]


@pytest.mark.slow
def test_a_batch_builds_the_good_specs_as_build_does_and_reports_the_bad_one(tmp_path):
    good = [write_spec(tmp_path, _small("small-a", 1), "a.yaml"), write_spec(tmp_path, _small("small-b", 3), "b.yaml")]
    bad = write_spec(tmp_path, {**_small("broken", 1), "grid": [2, 0, 1]}, "broken.yaml")
    result = CliRunner().invoke(cli, ["batch", str(good[0]), str(bad), str(good[1]), "-o", str(tmp_path / "batch"),
                                      "--jobs", "2"])
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    lines = result.output.splitlines()
    failed = [line for line in lines if "FAILED" in line]
    assert len(failed) == 1 and failed[0].startswith("broken") and "grid" in failed[0] and "error:" in failed[0]
    assert lines[-1] == "2 built, 1 failed"
    assert not (tmp_path / "batch" / "broken").exists()
    for spec, name in zip(good, ("small-a", "small-b"), strict=True):
        assert any(line.startswith(name) and " ok " in line for line in lines)
        ours = tmp_path / "batch" / name
        theirs = build(spec, output_dir=tmp_path / "build" / name, jobs=1, progress=Progress(False))
        theirs = tmp_path / "build" / name
        files = sorted(p.relative_to(theirs) for p in theirs.rglob("*") if p.is_file())
        assert sorted(p.relative_to(ours) for p in ours.rglob("*") if p.is_file()) == files
        assert any(str(f).startswith("pieces/") for f in files) and any(str(f).startswith("plates/") for f in files)
        for f in files:
            if f.name == "report.json":
                assert _report_without_times(ours / f) == _report_without_times(theirs / f)
            elif f.name == "report.md":
                assert _report_md_without_times(ours / f) == _report_md_without_times(theirs / f)
            else:
                assert (ours / f).read_bytes() == (theirs / f).read_bytes(), f


def test_two_specs_writing_one_folder_are_refused_before_any_work(tmp_path):
    a = write_spec(tmp_path, _small("same", 1), "a.yaml")
    b = write_spec(tmp_path, _small("same", 2), "b.yaml")
    result = CliRunner().invoke(cli, ["batch", str(a), str(b), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1
    assert result.output.strip().startswith("error: name:") and "same" in result.output
    assert len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_an_unreachable_scheduler_is_one_error_line(tmp_path):
    a = write_spec(tmp_path, _small("alone", 1), "a.yaml")
    result = CliRunner().invoke(cli, ["batch", str(a), "--scheduler", "tcp://127.0.0.1:9"])
    assert result.exit_code == 1
    assert result.output.strip().startswith("error: --scheduler: no Dask scheduler answers at tcp://127.0.0.1:9")
    assert len(result.output.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_stopped_batch_leaves_no_temporary_folder(tmp_path):
    # Ctrl-C or SIGTERM ends the local workers, and a build ended in its export leaves its temporary folder (seen:
    # `.NAME.tmp-*` beside the finished folders). Here the stop comes as the first spec finishes, and the second
    # spec's temporary folder is the one a worker killed in its export would leave: marked with a process that is gone
    import os
    import socket
    import subprocess
    import sys

    from volpuzzle.batch import run_batch
    from volpuzzle.export import MARKER

    specs = [write_spec(tmp_path, _small("first", 1), "a.yaml"), write_spec(tmp_path, _small("second", 3), "b.yaml")]
    root = tmp_path / "batch"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()

    def stop(_done, _total, result):
        left = root / f".{'second' if result.name == 'first' else 'first'}.tmp-abcd1234"
        left.mkdir(parents=True)
        (left / MARKER).write_text(json.dumps({"kind": "volpuzzle-output", "pid": dead.pid,
                                               "host": socket.gethostname()}))
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch([str(s) for s in specs], output_root=root, jobs=2, progress=stop)
    assert not [name for name in os.listdir(root) if ".tmp-" in name]


@pytest.mark.slow
def test_ctrl_c_on_a_batch_is_one_line(tmp_path):
    # Ctrl-C reaches the whole process group: the workers die of it, and Dask's nanny logged the broken shutdown as
    # an ERROR with a traceback before our "interrupted"
    import os
    import signal
    import subprocess
    import sys
    import time

    big = {**_small("big-a", 1), "grid": [4, 4, 4], "output": {"tolerance": 0.05}}
    specs = [write_spec(tmp_path, big, "a.yaml"), write_spec(tmp_path, {**big, "name": "big-b"}, "b.yaml")]
    proc = subprocess.Popen([sys.executable, "-m", "volpuzzle.cli", "batch", *map(str, specs), "-o",
                             str(tmp_path / "out"), "--jobs", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, cwd=tmp_path)
    time.sleep(7)  # the cluster started (~3 s) and both builds running (each ~10 s)
    assert proc.poll() is None, "the batch ended before the signal: the test needs longer builds"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.decode().strip() == "interrupted"
    out = tmp_path / "out"
    assert not (out.exists() and [name for name in os.listdir(out) if ".tmp-" in name])


@pytest.mark.slow
def test_a_batch_beside_another_cluster_prints_no_port_warning(tmp_path, capfd):
    # another Dask cluster (a notebook's, a second batch) holding port 8787 made ours warn in three lines on stderr
    import socket
    import warnings

    from volpuzzle.batch import run_batch

    spec = write_spec(tmp_path, _small("beside", 1), "a.yaml")
    holder = socket.socket()
    try:
        holder.bind(("", 8787))
        holder.listen(1)
    except OSError:
        pass  # already held by someone: the case itself
    try:
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            results = run_batch([str(spec)], output_root=tmp_path / "out", jobs=1)
    finally:
        holder.close()
    assert [r.ok for r in results] == [True]
    assert not [w for w in seen if "already in use" in str(w.message)]
    assert "already in use" not in capfd.readouterr().err


def _sigint_disposition():
    import signal

    return {signal.SIG_IGN: "ignored", signal.SIG_DFL: "default"}.get(signal.getsignal(signal.SIGINT), "handled")


@pytest.mark.slow
def test_the_local_workers_ignore_ctrl_c_and_this_process_keeps_its_handler():
    # Ctrl-C reaches the whole process group: a worker it caught printed a KeyboardInterrupt traceback from its
    # event loop (asyncio's handler) at any moment of a batch, beside our "interrupted"; this process ends them itself
    import signal

    from volpuzzle.batch import _client

    def mine(_signum, _frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGINT, mine)
    try:
        client, cluster = _client(1, None)
        try:
            assert signal.getsignal(signal.SIGINT) is mine
            assert set(client.run(_sigint_disposition).values()) == {"ignored"}
        finally:
            client.close()
            cluster.close()
    finally:
        signal.signal(signal.SIGINT, old)


def test_a_failed_spec_is_one_line_in_the_table_even_with_a_newline_in_its_path(tmp_path):
    # `build` flattens its message to one line; batch's result and table do the same (no cluster needed: build_one
    # is what each worker runs)
    from volpuzzle.batch import build_one, summary_table

    spec = tmp_path / "no\nthere.yaml"
    result = build_one(str(spec), None, False, "no\nthere")
    assert not result.ok and "\n" not in result.error and "spec: file not found" in result.error
    table = summary_table([result])
    assert len(table.splitlines()) == 3  # the head, the spec, the count
    assert "no there  FAILED" in table
