"""Issue 40 item 4 for the benches and the twin: no output is clobbered. A work folder (bench demos,
bench generalization, twin collect) is filled over several calls and never refused, but every file the
command writes there lands whole; a fresh output (bench overfit --out, bench twin --out, bench safety
--keep, twin run's summary files, calibrate check --rrd) and a file the user names (--plot) are
refused if they exist, before any work, unless --force."""

from __future__ import annotations

import json

import pytest

from equidiff_ros.cli import main


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _demos_bench_ready(tmp_path, monkeypatch, plot_bytes: bytes):
    """`bench demos --trained` with the roll-outs replaced by a result whose plot holds ``plot_bytes``: what
    the command writes, without the hours it measures."""
    from equidiff_core.benches import demos as bench_demos

    trained = tmp_path / "trained"
    for name in ("equidiff_1", "baseline_1"):
        (trained / name).mkdir(parents=True)
        (trained / name / "policy.pt").write_bytes(b"")

    def rolled_out(runs_dir, out, *args, **kwargs):
        plot = out / "success_vs_demos.png"
        plot.write_bytes(plot_bytes)
        return {"bench": "demos", "plot": str(plot), "minutes": {"eval": 0.0}}

    monkeypatch.setattr(bench_demos, "evaluate_runs", rolled_out)
    return ["bench", "demos", "--trained", str(trained), "--counts", "1", "--device", "cpu"]


def test_bench_demos_rewrites_its_own_result_whole_and_refuses_a_named_plot(tmp_path, monkeypatch, capsys):
    out, plot = tmp_path / "work", tmp_path / "figures" / "demos.png"
    argv = [*_demos_bench_ready(tmp_path, monkeypatch, b"first plot"), "--out", str(out), "--plot", str(plot)]
    assert main(argv) == 0
    assert json.loads((out / "result.json").read_text())["bench"] == "demos"
    assert plot.read_bytes() == b"first plot"
    capsys.readouterr()

    # the work folder is never refused; its result.json is renamed over the old one, not rewritten in place:
    # a reader holding the old file still reads it whole
    (out / "result.json").write_text('{"old": true}\n')
    with open(out / "result.json") as old_reader:
        plot.unlink()
        assert main(argv) == 0
        assert old_reader.read() == '{"old": true}\n'
    assert json.loads((out / "result.json").read_text())["bench"] == "demos"
    assert _listing(out) == ["result.json", "success_vs_demos.png"]  # no temporary left
    capsys.readouterr()

    # a plot the user named is refused before anything runs, left byte-identical; --force replaces it
    plot.write_bytes(b"someone's figure")
    monkeypatch.setattr(
        "equidiff_core.benches.demos.load_twin_job_configs", lambda *a: pytest.fail("refused after work began")
    )
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert (
        err == f"equidiff bench demos: {plot} exists; not replacing it (pass --force to replace it, or choose "
        "another output)\n"
    )
    assert plot.read_bytes() == b"someone's figure"
    monkeypatch.undo()
    argv = [*_demos_bench_ready(tmp_path / "again", monkeypatch, b"second plot"), "--out", str(out)]
    assert main([*argv, "--plot", str(plot), "--force"]) == 0
    assert plot.read_bytes() == b"second plot"
    assert _listing(plot.parent) == ["demos.png"]
