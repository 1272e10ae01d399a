"""Operator-driven calibration poses: the SpaceMouse moves the arm, a button takes a sample.

The same teleoperation as data collection (``lab.teleop.TeleopIntegrator``: deadzone, speed
scaling, target kept in the workspace box and at most 5 cm ahead of the measured TCP), sent at
``rate_hz`` as one-step chunks to franka_node's control loop (``capture.ControlledArm``), as
teleop_node sends them to franka_node: the safety box, cone and speed limits apply. Left
button: hold still, wait for the arm to rest, capture every camera. Right button: finish.
"""

from __future__ import annotations

import time

from ..config import Workspace
from ..lab.teleop import (
    SpaceMouseSource,
    TeleopConfig,
    TeleopInput,
    TeleopIntegrator,
    is_fresh,
)
from .board import BoardDetector, BoardSpec, CalibrationError
from .capture import ControlledArm, Grab
from .solve import Sample

CAPTURE_BUTTON = 0
FINISH_BUTTON = 1


def capture_operator(
    arm: ControlledArm,
    grab: Grab,
    spec: BoardSpec,
    workspace: Workspace,
    log=print,
    source: SpaceMouseSource | None = None,
    rate_hz: float = 100.0,
    min_samples: int = 8,
) -> list[Sample]:
    """Send SpaceMouse motion to ``arm``'s control loop until the finish button; a sample per capture press."""
    source = source or SpaceMouseSource()
    integrator = TeleopIntegrator(TeleopConfig(source="spacemouse", rate_hz=max(rate_hz, 100.0)), workspace)
    detector = BoardDetector(spec)
    samples: list[Sample] = []
    # chunks go out at teleop_node's rate (20 Hz); the loop integrates the device at rate_hz
    send_every, tick = max(1, round(rate_hz / integrator.config.publish_hz)), 0
    last_warning = -float("inf")

    def offer(chunk) -> None:
        """Like teleop_node's chunks, one the loop refuses (late, tilted past the cone) is dropped:
        the arm holds, the operator is told; a stop (error, divergence) ends the calibration."""
        nonlocal last_warning
        if not arm.offer(chunk) and time.monotonic() - last_warning > 2.0:
            last_warning = time.monotonic()
            log(f"the control loop refused the SpaceMouse target ({arm.controller.stats.last_rejection}); holding")

    arm.start()
    source.connect()
    try:
        integrator.reset(arm.tcp_pose())
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
                # the newest target (where the filter keeps it), held there while the arm settles
                offer(arm.glide(arm.limits.clamp(integrator.target)))
                measured = arm.wait_at_rest()
                frames = grab(None)
                dets = {n: d for n, d in ((n, detector.detect(img)) for n, img in frames.items()) if d is not None}
                samples.append(Sample(measured, dets))
                log(
                    f"sample {len(samples)}: board corners "
                    + ", ".join(f"{n} {len(dets[n]) if n in dets else 0}" for n in frames)
                )
                integrator.reset(arm.tcp_pose())
                continue
            integrator.observe(arm.tcp_pose())
            fresh = is_fresh(inp, now, integrator.config.input_timeout_s)  # a silent device: hold
            integrator.step(inp if fresh else None, dt)
            tick += 1
            if tick % send_every == 0:
                offer(integrator.chunk(arm.controller.clock.now_ns()))
            time.sleep(max(0.0, dt - (time.monotonic_ns() - now) / 1e9))
    except KeyboardInterrupt as err:
        raise CalibrationError("calibration aborted by the operator") from err
    finally:
        source.disconnect()
    return samples
