"""Operator-driven calibration poses: the SpaceMouse moves the arm, a button takes a sample.

The same teleoperation as data collection (``teleop.TeleopIntegrator``: deadzone, speed
scaling, target kept in the workspace box and at most 5 cm ahead of the measured TCP),
streamed straight to the franky backend's impedance tracker at ``rate_hz``. Left button: hold
still, wait for the arm to rest, capture every camera. Right button: finish.
"""

from __future__ import annotations

import time

import numpy as np

from ..config import Workspace
from ..teleop import (
    SpaceMouseSource,
    TeleopConfig,
    TeleopInput,
    TeleopIntegrator,
    is_fresh,
)
from .board import BoardDetector, BoardSpec, CalibrationError
from .capture import Grab
from .solve import Sample

CAPTURE_BUTTON = 0
FINISH_BUTTON = 1


def capture_operator(
    arm,
    grab: Grab,
    spec: BoardSpec,
    workspace: Workspace,
    log=print,
    source: SpaceMouseSource | None = None,
    rate_hz: float = 100.0,
    min_samples: int = 8,
) -> list[Sample]:
    """Stream SpaceMouse motion to ``arm.robot`` until the finish button; a sample per capture press."""
    source = source or SpaceMouseSource()
    integrator = TeleopIntegrator(TeleopConfig(source="spacemouse", rate_hz=max(rate_hz, 100.0)), workspace)
    detector = BoardDetector(spec)
    robot = arm.robot
    samples: list[Sample] = []
    source.connect()
    robot.start_streaming()
    try:
        integrator.reset(robot.read_state().ee_pose)
        log("SpaceMouse: move the board into view of every camera; left button = capture, right = finish")
        previous: tuple[int, ...] = ()
        dt = 1.0 / rate_hz
        while True:
            now = time.monotonic_ns()
            inp = source.read(now)
            pressed = {b for b, v in enumerate(inp.buttons) if v and (b >= len(previous) or not previous[b])}
            previous = inp.buttons
            if FINISH_BUTTON in pressed:
                if len(samples) >= min_samples:
                    break
                log(f"{len(samples)} samples so far; take at least {min_samples} before finishing")
            if CAPTURE_BUTTON in pressed:
                hold = TeleopInput((0.0,) * 6, (), now)
                integrator.step(hold, dt)
                measured = arm.wait_at_rest()
                frames = grab(None)
                dets = {n: d for n, d in ((n, detector.detect(img)) for n, img in frames.items()) if d is not None}
                samples.append(Sample(measured, dets))
                log(
                    f"sample {len(samples)}: board corners "
                    + ", ".join(f"{n} {len(dets[n]) if n in dets else 0}" for n in frames)
                )
                integrator.reset(robot.read_state().ee_pose)
                continue
            state = robot.read_state()
            integrator.observe(state.ee_pose)
            fresh = is_fresh(inp, now, integrator.config.input_timeout_s)  # a silent device: hold
            target, _ = integrator.step(inp if fresh else None, dt)
            robot.stream_target(target, np.zeros(3), np.zeros(3))
            time.sleep(max(0.0, dt - (time.monotonic_ns() - now) / 1e9))
    except KeyboardInterrupt as err:
        raise CalibrationError("calibration aborted by the operator") from err
    finally:
        robot.stop_streaming()
        source.disconnect()
    return samples
