"""What the core's jobs (training, benches, checks) share with whoever runs them: the error they raise and
where their progress lines go.

A job takes typed settings (a frozen dataclass or plain parameters) and returns its result; it reports
progress through its module's logger (under ``equidiff_core``) and fails by raising ``JobError`` or its
domain's subclass. Its caller, the ``equidiff`` CLI or a job's own ``python -m`` entry, prints the result,
shows the progress lines with ``progress_lines`` and turns an error into its message and exit status with
``error_message``. This module imports nothing heavy: the CLI loads it before any command.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

CORE_LOGGER = "equidiff_core"


class JobError(Exception):
    """A job could not do what it was asked.

    ``str(err)`` is the message the command prints after ``equidiff <command>: `` (it may span lines);
    ``exit_status`` is the command's exit status: 2 when the request itself is wrong (conflicting or
    out-of-range settings, inputs that are missing or do not fit), 1 when the work failed."""

    def __init__(self, message: str, exit_status: int = 1):
        super().__init__(message)
        self.exit_status = exit_status


class _ProgressHandler(logging.Handler):
    """Each record as one line, ``prefix`` + message, on the stream named when it is written (so that a
    stream replaced after the handler was installed, as tests do, receives it)."""

    def __init__(self, stream: str, prefix: str):
        super().__init__(logging.INFO)
        self.stream, self.prefix = stream, prefix

    def emit(self, record: logging.LogRecord) -> None:
        try:
            stream = sys.stderr if self.stream == "stderr" else sys.stdout
            stream.write(f"{self.prefix}{record.getMessage()}\n")
            stream.flush()
        except (OSError, ValueError):  # a closed stream must not stop the job
            self.handleError(record)


@contextlib.contextmanager
def progress_lines(stream: str = "stdout", prefix: str = "") -> Iterator[None]:
    """While inside, the core's progress (its loggers' INFO records and above) is printed as plain lines,
    ``prefix`` + message, on ``stream`` ("stdout" or "stderr"): what the commands printed before the core
    logged. Restores the core logger's level and handlers on exit."""
    logger = logging.getLogger(CORE_LOGGER)
    handler = _ProgressHandler(stream, prefix)
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def error_message(err: BaseException) -> tuple[str, int] | None:
    """``err``'s message and exit status, for its caller to print after ``equidiff <command>: ``: a
    ``JobError``'s own, 2 for a bad config file or value (``ConfigError``, on one line) and for an output that
    exists already (``OutputExistsError``); None for any other error (a bug: its traceback is worth more than a
    line)."""
    # checked by module, so that this module (and `equidiff --help`) does not import the config module
    config = sys.modules.get("equidiff_core.config")
    outputs = sys.modules.get("equidiff_core.runtime.output_files")
    if isinstance(err, JobError):
        return str(err), err.exit_status
    if (config is not None and isinstance(err, config.ConfigError)) or (
        outputs is not None and isinstance(err, outputs.OutputExistsError)
    ):
        return " ".join(str(err).split()), 2
    return None
