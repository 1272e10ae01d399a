"""Issue 40 item 4 for the benches and the twin: no output is clobbered. A work folder (bench demos,
bench generalization, twin collect) is filled over several calls and never refused, but every file the
command writes there lands whole; a fresh output (bench overfit --out, bench twin --out, bench safety
--keep, twin run's summary files, calibrate check --rrd) and a file the user names (--plot) are
refused if they exist, before any work, unless --force."""

from __future__ import annotations

import argparse
import json

import pytest

from equidiff_ros.cli import COMMANDS, build_parser, main

# the options that name what a command writes
WRITES = ("--out", "-o", "--output", "--plot", "--keep", "--rrd")
# commands whose output option names a work folder, filled over several calls: never refused, so no --force
WORK_FOLDERS = {
    ("bench", "generalization"): "--out holds the demos, the runs trained in parts and the roll-outs of earlier "
    "calls; each file the bench writes there (result.json, rollouts_*.json) lands whole",
    ("twin", "collect"): "--out: each call adds its bags, numbered after those there, never overwriting one",
}
# commands with a --force of another meaning whose output is never replaced at all
NEVER_REPLACED = {
    ("bags", "repair"): "an existing --output is always refused (bags.repair_bag); --force rewrites a bag that "
    "reads fine",
}


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _demos_bench_ready(tmp_path, monkeypatch, plot_bytes: bytes):
    """`bench demos --trained` with the roll-outs replaced by a result whose plot holds ``plot_bytes``: what
    the command writes, without the hours it measures."""
    from equidiff_core.benches import sample_efficiency as bench_demos

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
        "equidiff_core.benches.sample_efficiency.load_twin_job_configs",
        lambda *a: pytest.fail("refused after work began"),
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


def _occupied(folder, content=b"an earlier run's"):
    folder.mkdir(parents=True)
    (folder / "kept.bin").write_bytes(content)
    return folder


def test_bench_overfit_refuses_an_existing_out_then_replaces_it_with_force(tmp_path, capsys):
    out = _occupied(tmp_path / "overfit")
    argv = ["bench", "overfit", "--preset", "tiny", "--steps", "1", "--noise-repeats", "1", "--out", str(out)]
    assert main(argv) == 2  # before any training
    out_text, err = capsys.readouterr()
    assert (
        out_text == ""
        and err.startswith(f"equidiff bench overfit: {out} exists; not replacing it")
        and err.count("\n") == 1
    )
    assert (
        _listing(tmp_path) == ["overfit", "overfit/kept.bin"] and (out / "kept.bin").read_bytes() == b"an earlier run's"
    )

    assert main([*argv, "--force"]) == 3  # one step fits nothing: the gate fails, the run is kept all the same
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["steps"] == 1
    assert (out / "run" / "policy.pt").is_file() and (out / "untrained.pt").is_file()
    assert not (out / "kept.bin").exists()  # replaced, not merged
    assert [p.name for p in tmp_path.iterdir()] == ["overfit"]  # no temporary left beside it


def test_bench_twin_refuses_an_existing_out_before_the_twin_starts(tmp_path, monkeypatch, capsys):
    from equidiff_ros.benches import twin as bench_twin

    monkeypatch.setattr(bench_twin, "TwinStack", lambda *a, **k: pytest.fail("the twin started"))
    monkeypatch.setattr(bench_twin, "resolve_policy", lambda *a, **k: pytest.fail("a policy was built"))
    out = _occupied(tmp_path / "twin")
    assert main(["bench", "twin", "--standin", "--out", str(out)]) == 2
    assert capsys.readouterr().err.startswith(f"equidiff bench twin: {out} exists; not replacing it")
    assert _listing(tmp_path) == ["twin", "twin/kept.bin"] and (out / "kept.bin").read_bytes() == b"an earlier run's"


def test_bench_safety_refuses_an_existing_keep_before_anything_starts(tmp_path, monkeypatch):
    from equidiff_core.benches.fault_campaign import driver
    from equidiff_core.runtime.output_files import OutputExistsError

    monkeypatch.setenv("ROS_DOMAIN_ID", "117")
    monkeypatch.setattr(driver, "run_campaign", lambda *a, **k: pytest.fail("the campaign started"))
    keep = _occupied(tmp_path / "safety")
    with pytest.raises(OutputExistsError, match="pass --force"):
        driver.run_bench("nan", None, keep=keep)  # no probe: nothing of the ROS side is needed to refuse
    assert _listing(tmp_path) == ["safety", "safety/kept.bin"]


class _NoTwin:
    """A TwinStack that starts nothing: the run's episodes are not what these tests are about."""

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_twin_run_refuses_its_summary_files_before_the_twin_starts(tmp_path, monkeypatch, capsys):
    from equidiff_ros.twin import main_job

    monkeypatch.setattr(main_job, "TwinStack", lambda *a, **k: pytest.fail("the twin started"))
    monkeypatch.setattr(main_job, "resolve_policy", lambda *a, **k: pytest.fail("a policy was built"))
    out = tmp_path / "run"
    out.mkdir()
    (out / "bags").mkdir()  # an earlier run's bags: kept, and no reason to refuse
    (out / "twin_run.rrd").write_bytes(b"an earlier recording")
    assert main(["twin", "run", "--standin", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"equidiff twin run: {out / 'twin_run.rrd'} exists; not replacing it (pass --force")
    assert (out / "twin_run.rrd").read_bytes() == b"an earlier recording"

    (out / "summary.json").write_text('{"episodes": 5}\n')  # refused even when no recording is asked for
    assert main(["twin", "run", "--standin", "--no-rrd", "--out", str(out)]) == 2
    assert f"{out / 'summary.json'} exists" in capsys.readouterr().err
    assert _listing(out) == ["bags", "summary.json", "twin_run.rrd"]

    # --force: the run goes on, and its summary is renamed over the old one when it ends
    monkeypatch.setattr(main_job, "TwinStack", _NoTwin)
    monkeypatch.setattr(main_job, "resolve_policy", lambda *a, **k: (tmp_path / "policy.pt", "stand-in"))
    with open(out / "summary.json") as old_reader:
        assert main(["twin", "run", "--standin", "--episodes", "0", "--out", str(out), "--force"]) == 0
        assert old_reader.read() == '{"episodes": 5}\n'
    assert json.loads((out / "summary.json").read_text())["episodes"] == 0
    assert _listing(out) == ["bags", "summary.json", "twin_run.rrd"]  # no temporary left


def test_calibrate_check_refuses_an_existing_rrd_before_capturing(tmp_path, monkeypatch, capsys):
    from equidiff_core.calibration import job as calibration_job

    monkeypatch.setattr(calibration_job, "_twin_capture", lambda *a, **k: pytest.fail("captured"))
    rrd = tmp_path / "check.rrd"
    rrd.write_bytes(b"an earlier check")
    assert main(["calibrate", "check", "--twin", "--direct", "--rrd", str(rrd)]) == 2
    assert capsys.readouterr().err.startswith(f"equidiff calibrate check: {rrd} exists; not replacing it")
    assert rrd.read_bytes() == b"an earlier check" and _listing(tmp_path) == ["check.rrd"]


def _leaf_parser(path: tuple[str, ...]) -> argparse.ArgumentParser:
    parser = build_parser(list(path))
    for name in path:
        subcommands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = subcommands.choices[name]
    return parser


@pytest.mark.parametrize("path", list(COMMANDS), ids=" ".join)
def test_every_command_that_writes_can_be_told_to_replace(path):
    """Every command with an output option refuses an existing output unless --force (its help says it
    replaces), except the work folders and the one that never replaces, listed above with the reason."""
    options = {option: action for action in _leaf_parser(path)._actions for option in action.option_strings}
    writes = sorted(set(WRITES) & set(options))
    if path in WORK_FOLDERS:
        assert writes and "--force" not in options, f"{' '.join(path)}: {WORK_FOLDERS[path]}"
    elif path in NEVER_REPLACED:
        assert writes and "replace" not in options["--force"].help, NEVER_REPLACED[path]
    elif writes:
        assert "--force" in options, f"equidiff {' '.join(path)} writes {writes} but takes no --force"
        assert "replace" in options["--force"].help, options["--force"].help


def test_the_exceptions_are_real_commands():
    assert set(WORK_FOLDERS) | set(NEVER_REPLACED) <= set(COMMANDS)
