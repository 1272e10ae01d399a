"""What the core's jobs share with their callers: progress lines as the commands printed them, and errors
turned into the commands' messages and exit statuses."""

import logging

from equidiff_core.config import ConfigError
from equidiff_core.runtime.jobs import JobError, progress_lines
from equidiff_ros.cli import report_error


def test_progress_lines_print_the_core_loggers_records_while_inside(capsys):
    log = logging.getLogger("equidiff_core.some_job")
    with progress_lines("stderr", "equidiff train: "):
        log.info("2 train episodes")
    with progress_lines():
        log.info("[bench] roll-outs reused")
    log.info("after: not shown")
    out = capsys.readouterr()
    assert out.err == "equidiff train: 2 train episodes\n" and out.out == "[bench] roll-outs reused\n"
    assert not logging.getLogger("equidiff_core").handlers  # nothing left behind for the next command


def test_errors_become_the_commands_message_and_exit_status(capsys):
    assert report_error("bench demos", JobError("no demos\nrerun with --demos-dir d", 2)) == 2
    assert capsys.readouterr().err == "equidiff bench demos: no demos\nrerun with --demos-dir d\n"
    assert report_error("train", JobError("no usable episodes")) == 1
    assert report_error("train", ConfigError("lab.yaml:\n  bad   value")) == 2
    assert capsys.readouterr().err.splitlines()[-1] == "equidiff train: lab.yaml: bad value"
    assert report_error("train", ValueError("a bug")) is None and capsys.readouterr().err == ""
