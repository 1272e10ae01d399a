"""The operator loop's terminal screen (``equidiff lab``; its help text says what it shows and does): the loop
(``equidiff_core.lab.operator_loop``) behind one lock, fed by the ROS client (``lab_client``) and prompt_toolkit's keys.

Built on prompt_toolkit: a full-screen application with raw single-key bindings and a periodic
redraw, already installed with the ROS tooling (IPython's dependency), so the lab needs nothing
new; textual would add a second UI framework for a one-window screen.
"""

from __future__ import annotations

import os
import queue
import sys
import threading
import time

from equidiff_core.lab.operator_loop import LoopConfig, OperatorLoop, Request
from equidiff_ros.lab_client import LabClient, LabError

REDRAW_S = 0.25
STYLE = {
    "title": "bold",
    "ok": "ansigreen bold",
    "warn": "ansiyellow bold",
    "bad": "ansired bold",
    "dim": "ansibrightblack",
    "key": "reverse",
}


class Screen:
    """The loop behind one lock: keys (UI thread), node values (ROS thread) and answers (worker thread)."""

    def __init__(self, loop: OperatorLoop, lab):
        self.loop, self.lab = loop, lab
        self.lock = threading.Lock()
        self.requests: queue.Queue[Request | None] = queue.Queue()
        self.app = None
        self.worker = threading.Thread(target=self._work, name="lab-requests", daemon=True)

    def on_value(self, name: str, value) -> None:
        with self.lock:
            self.loop.observe(name, value, time.monotonic())
        self.redraw()

    def on_key(self, key: str) -> None:
        with self.lock:
            self._send(self.loop.press(key, time.monotonic()))
            quit_now = self.loop.quit
        if quit_now and self.app is not None:
            self.app.exit()

    def on_escape(self) -> None:
        with self.lock:
            key = "c" if self.loop.confirming is None else "n"
        self.on_key(key)

    def text(self):
        with self.lock:
            self._send(self.loop.tick(time.monotonic()))
            return [(f"class:{style}" if style else "", text) for style, text in self.loop.render(time.monotonic())]

    def _send(self, requests: list[Request]) -> None:
        for request in requests:
            self.requests.put(request)

    def _work(self) -> None:
        while (request := self.requests.get()) is not None:
            try:
                ok, message = True, self.lab.call(request.srv_type, request.service, **request.fields)
            except LabError as err:
                ok, message = False, str(err)
            except Exception as err:  # noqa: BLE001 - the screen outlives any failed call, and says what failed
                ok, message = False, f"{type(err).__name__}: {err}"
            with self.lock:
                self._send(self.loop.done(request, ok, message, time.monotonic()))
            self.redraw()

    def redraw(self) -> None:
        if self.app is not None:
            self.app.invalidate()

    def stop(self) -> None:
        self.requests.put(None)
        self.worker.join(timeout=20.0)


def run_lab_screen(args) -> int:
    """``equidiff lab`` for its parsed arguments: the screen until the operator quits; the exit code."""
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        print(
            "equidiff lab: the screen needs a terminal; scripts use equidiff lab record|policy|home|ack|status",
            file=sys.stderr,
        )
        return 2
    try:  # the ros extra's: checked here so that a missing one is named, not a traceback
        import prompt_toolkit  # noqa: F401
    except ImportError:
        print("equidiff lab: the screen needs prompt_toolkit (the package's `ros` extra)", file=sys.stderr)
        return 2
    from prompt_toolkit import Application
    from prompt_toolkit.key_binding import KeyBindings
    from prompt_toolkit.keys import Keys
    from prompt_toolkit.layout import FormattedTextControl, Layout, Window
    from prompt_toolkit.styles import Style

    config = LoopConfig(
        reset_s=args.reset_s,
        auto_start=args.auto_start,
        home_after_episode=not args.no_home,
        output_dir=args.output_dir,
    )
    loop = OperatorLoop(config)
    loop.say(f"watching the nodes on ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}")
    with LabClient() as lab:
        screen = Screen(loop, lab)
        keys = KeyBindings()

        @keys.add(Keys.Any)
        def _key(event):
            screen.on_key(event.data)

        @keys.add("escape", eager=True)
        def _escape(event):  # the reflex key for "no" or "stop counting"
            screen.on_escape()

        @keys.add("c-c")
        def _interrupt(event):
            event.app.exit()

        screen.app = Application(
            layout=Layout(Window(FormattedTextControl(screen.text, focusable=True), wrap_lines=True)),
            key_bindings=keys,
            style=Style.from_dict(STYLE),
            full_screen=True,
            refresh_interval=REDRAW_S,
        )
        screen.worker.start()
        lab.watch(screen.on_value)
        try:
            screen.app.run()
        finally:
            screen.stop()
    return 0
