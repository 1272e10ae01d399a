"""The GPU check: inference, training and DDP on CUDA measured in one command, one JSON file.

    bash scripts/gpu_check.sh                       # on the GPU machine (H100/H200), <= 8 minutes
    bash scripts/gpu_check.sh --device cpu --tiny   # the rehearsal here: the same code paths, tiny sizes
    bash scripts/gpu_check.sh --dry-run             # every part's command parsed by the CLI, nothing run
    python scripts/gpu_check.py verify DIR          # here, on what came back: the GPU-trained files load on the CPU
    python scripts/gpu_check.py size [--carry P...] # what a device call would send (the 64 MiB limit)

``run`` (what gpu_check.sh calls) runs each part as the ``equidiff`` command a user would type, in
its own process with a time limit, so a part that fails or hangs costs only itself; after every
part the JSON file (and the log, and the trained files) is written again, to ``--json`` and to
``$OUT`` when set, so a run cut short still returns what it measured. Parts, in order of priority,
each skipped when the remaining budget is below its minimum:

1. ``bench policy --rtc`` for ``paper`` and ``compact`` in the modes bf16 traced, bf16 traced +
   CUDA graph, fp32 traced, fp32 traced + CUDA graph (one process per preset: one export); the
   graph modes' actions against the same mode without the graph;
2. ``torchrun --nproc-per-node 1`` training (NCCL on CUDA, gloo on the CPU): a group of one runs
   the collectives and DDP of N GPUs; its checkpoint must load on the CPU with rank 0's digest;
3. ``bench train`` for paper and compact EquiDiff: bf16, fp32 and bf16 through the CPU DataLoader;
4. a short real training from the carried packed dataset: the loss must fall, the checkpoint is
   copied to ``$OUT`` (``train_policy.pt``, ``train_last.ckpt`` without optimiser state) and loaded
   on the CPU;
5. ``bench train`` for the baselines (bf16, fp32).

Only the standard library is imported at module level: ``size`` runs with any Python.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as package_version
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CARRY = ROOT / ".gpu_carry"
DEVICE_TREE_LIMIT = 64 * 1024 * 1024  # what one device call may send: the tree plus the carried paths
OUT_FILE_LIMIT = 16 * 1024 * 1024  # one file back from $OUT
PAPER_P99_GOAL_MS = 15.0  # the goal: paper preset p99 on an H100
RTC_GOAL = 1.2  # RTC-guided sampling at most 1.2x plain DDIM
GPU_BUSY_GOAL_PCT = 90.0
INFERENCE_MODES = "bf16-traced,bf16-traced-graph,fp32-traced,fp32-traced-graph"
FALLBACK_GRAPH_MODE = "bf16-eager-graph"  # tried when the traced graph mode fails: is it TorchScript or the graph?


@dataclass
class Sizes:
    """What the parts run at: the GPU's sizes, or tiny ones for the CPU rehearsal."""

    presets: tuple[str, str]  # (in the role of paper, in the role of compact)
    iters: tuple[int, int]
    eager_iters: int
    bench_steps: int
    bench_warmup: int
    bench_batch: int
    ddp_steps: int
    ddp_batch: int
    train_preset: str
    train_steps: int
    train_minutes: float
    train_batch: int
    train_lr: float
    train_warmup: int
    train_eval_every: int
    eval_samples: int
    bench_runs: str  # bench train's --runs for EquiDiff
    budget_s: float
    timeout_scale: float  # part time limits are sized for the GPU machine; a shared 2-core CPU is slower


GPU_SIZES = Sizes(
    presets=("paper", "compact"),
    iters=(100, 60),  # p99 of 100 DDIM-16 calls for the headline figure
    eager_iters=3,
    bench_steps=5,
    bench_warmup=2,
    bench_batch=64,  # the paper's batch
    ddp_steps=6,
    ddp_batch=16,
    train_preset="compact",
    train_steps=2000,  # the cosine schedule's length; --max-minutes stops it first
    train_minutes=2.0,
    train_batch=64,
    train_lr=1e-4,
    train_warmup=50,
    train_eval_every=250,
    eval_samples=8,
    bench_runs="bf16,fp32,bf16:loader",
    budget_s=450,  # of the device's 8-minute command: wheels, start-up and the last writes fit in the rest
    timeout_scale=1.0,
)
# the rehearsal: every command once (both presets are tiny), a few steps each; no budget cut on a slow CPU
TINY_SIZES = Sizes(
    presets=("tiny", "tiny"),
    iters=(3, 3),
    eager_iters=0,
    bench_steps=1,
    bench_warmup=1,
    bench_batch=2,
    ddp_steps=2,
    ddp_batch=2,
    train_preset="tiny",
    train_steps=8,
    train_minutes=5.0,
    train_batch=4,
    train_lr=1e-3,
    train_warmup=1,
    train_eval_every=8,  # once, at the end
    eval_samples=2,
    bench_runs="bf16,fp32:device",  # bf16 goes through the loader on a CPU already
    budget_s=3600,
    timeout_scale=6.0,
)


@dataclass
class Part:
    name: str
    argv: list[str]
    timeout_s: float
    min_s: float  # skipped when less of the budget is left
    after: object = None  # callable(stdout JSON or None, Check) -> dict merged into the part's result
    fallback: Part | None = None  # run when this part's traced CUDA graph failed: TorchScript or the graph?


class Check:
    def __init__(self, args):
        self.device = args.device
        self.sizes = TINY_SIZES if (args.tiny or args.device == "cpu") else GPU_SIZES
        self.budget_s = args.budget_s or self.sizes.budget_s
        self.work = Path(args.work).resolve()
        self.json_path = Path(
            args.json
            or (ROOT / "docs/results/gpu_check.json" if args.device == "cuda" else self.work / "gpu_check.json")
        )
        self.out = Path(os.environ["OUT"]) if os.environ.get("OUT") else None
        self.packed = Path(args.packed).resolve() if args.packed else CARRY / "packed"
        self.started = time.monotonic()
        self.log_path = self.work / "gpu_check.log"
        self.results: dict = {
            "check": "gpu_check",
            "version": 1,
            "device": args.device,
            "rehearsal": args.device != "cuda",
            "sizes": "tiny" if self.sizes is TINY_SIZES else "gpu",
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "budget_s": self.budget_s,
            "parts": {},
        }

    def left_s(self) -> float:
        return self.budget_s - (time.monotonic() - self.started)

    def cli(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "equidiff_ros.cli", *args]

    def log(self, text: str) -> None:
        with self.log_path.open("a") as f:
            f.write(text if text.endswith("\n") else text + "\n")

    def save(self) -> None:
        self.results["elapsed_s"] = round(time.monotonic() - self.started, 1)
        self.results.update(summarize(self.results))
        text = json.dumps(self.results, indent=1) + "\n"
        self.json_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.json_path.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(self.json_path)
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            (self.out / "gpu_check.json").write_text(text)
            shutil.copyfile(self.log_path, self.out / "gpu_check.log")


def last_json_line(text: str) -> dict | None:
    for raw in reversed(text.splitlines()):
        line = raw.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return None


def run_part(check: Check, part: Part) -> dict:
    left = check.left_s()
    if left < part.min_s:
        return {"status": "skipped", "reason": f"{left:.0f} s of the budget left, needs {part.min_s:.0f} s"}
    timeout = min(part.timeout_s * check.sizes.timeout_scale, left)
    check.log(f"\n===== {part.name}: {' '.join(part.argv)}  (limit {timeout:.0f} s)")
    t0 = time.monotonic()
    # its own process group: a timeout ends the part's whole tree (torchrun's workers too), nothing else
    proc = subprocess.Popen(
        part.argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        start_new_session=True,
    )
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        rc = None
    seconds = round(time.monotonic() - t0, 1)
    check.log(stdout)
    check.log(stderr[-20000:])
    out = {"seconds": seconds}
    if rc is None:
        out.update(status="timeout", error=f"killed after {timeout:.0f} s")
    elif rc != 0:
        tail = [ln for ln in stderr.strip().splitlines() if ln.strip()][-3:]
        out.update(status="error", error=f"exit {rc}: " + " | ".join(tail))
    else:
        out["status"] = "ok"
    parsed = last_json_line(stdout)
    if parsed is not None:
        out["result"] = parsed
    if part.after is not None and out["status"] == "ok":
        try:
            out.update(part.after(parsed, check))
        except Exception as err:  # noqa: BLE001 - a failed check is a result, not a crash of the whole run
            out.update(status="error", error=f"check after the run: {type(err).__name__}: {err}")
    graph = (parsed or {}).get("modes", {}).get("bf16-traced-graph", {})
    if part.fallback is not None and out["status"] == "ok" and "error" in graph:
        out["fallback"] = run_part(check, part.fallback)
    return out


def options(**values) -> list[str]:
    """``options(eval_every=5, no_progress=True)`` -> ``["--eval-every", "5", "--no-progress"]``."""
    argv = []
    for key, value in values.items():
        flag = "--" + key.replace("_", "-")
        argv += [flag] if value is True else [flag, str(value)]
    return argv


def plan(check: Check) -> list[Part]:
    s, dev, work = check.sizes, check.device, check.work
    parts = []
    roles: dict[str, tuple[str, int]] = {}  # preset -> (role, iters); the rehearsal's two tiny presets run once
    for role, preset, iters in zip(("paper", "compact"), s.presets, s.iters):
        roles.setdefault(preset, (role, iters))
    for preset, (role, iters) in roles.items():
        threads = 4 if dev == "cuda" else 1  # the host side of GPU inference; the CPU rehearsal shares 2 cores
        policy_bench = options(
            device=dev, preset=preset, rtc=True, iters=iters, eager_iters=s.eager_iters, threads=threads
        )
        parts.append(
            Part(
                f"policy_{role}",
                check.cli("bench", "policy", *policy_bench, "--modes", INFERENCE_MODES),
                timeout_s=150,
                min_s=30,
                fallback=Part(
                    f"policy_{role} {FALLBACK_GRAPH_MODE} fallback",
                    check.cli("bench", "policy", *policy_bench, "--modes", FALLBACK_GRAPH_MODE),
                    timeout_s=90,
                    min_s=30,
                ),
            )
        )
    train_options = options(
        preset=s.train_preset,
        checkpoint_every=0,
        val_fraction=0,
        device=dev,
        no_progress=True,
        cache_dir=work / "cache",
    )
    ddp_out = work / "ddp"
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "1"]
    parts.append(
        Part(
            "ddp",
            [*torchrun, "-m", "equidiff_ros.cli", "train", str(check.packed), "--out", str(ddp_out), *train_options]
            + options(steps=s.ddp_steps, batch_size=s.ddp_batch, warmup_steps=1, eval_every=s.ddp_steps)
            + options(eval_max_samples=2),
            timeout_s=150,
            min_s=40,
            after=lambda _, c: {"check": check_ddp(ddp_out)},
        )
    )
    for preset in dict.fromkeys(s.presets):  # the rehearsal's presets are both tiny: measured once
        parts.append(_bench_train(check, preset, "equidiff", s.bench_runs))
    train_out = work / "train"
    parts.append(
        Part(
            "training",
            check.cli("train", str(check.packed), "--out", str(train_out), *train_options)
            + options(
                steps=s.train_steps,
                max_minutes=s.train_minutes,
                batch_size=s.train_batch,
                lr=s.train_lr,
                warmup_steps=s.train_warmup,
                eval_every=s.train_eval_every,
                eval_max_samples=s.eval_samples,
            ),
            timeout_s=60 * s.train_minutes + 120,
            min_s=60 * s.train_minutes + 40,
            after=lambda _, c: collect_training(c, train_out),
        )
    )
    for preset in dict.fromkeys(s.presets):
        parts.append(_bench_train(check, preset, "baseline", "bf16,fp32"))
    return parts


def _bench_train(check: Check, preset: str, policy: str, runs: str) -> Part:
    s = check.sizes
    bench = options(
        device=check.device,
        preset=preset,
        policy=policy,
        runs=runs,
        batch_size=s.bench_batch,
        cuda_batch_size=s.bench_batch,
        steps=s.bench_steps,
        warmup=s.bench_warmup,
        samples=s.bench_batch,
    )
    return Part(f"train_bench_{preset}_{policy}", check.cli("bench", "train", *bench), timeout_s=180, min_s=30)


def collect_training(check: Check, run_dir: Path) -> dict:
    """The loss curve of the short training; its files copied where they come back, then loaded on the CPU."""
    history = json.loads((run_dir / "history.json").read_text())
    losses = [h["loss"] for h in history if "loss" in h]
    k = max(1, len(losses) // 10)
    first, last = sum(losses[:k]) / k, sum(losses[-k:]) / k
    rows = [h for h in history if "sec_per_step" in h]
    out = {
        "steps": max((h["step"] for h in history if "loss" in h), default=0),
        "loss_first": round(first, 5),
        "loss_last": round(last, 5),
        "loss_fell": last < first,
        "sec_per_step": round(sum(h["sec_per_step"] for h in rows[1:]) / max(1, len(rows) - 1), 4),
        "history": [{"step": h["step"], "loss": round(h["loss"], 5)} for h in history if "loss" in h][
            :: max(1, len(losses) // 20)
        ],
    }
    evals = [h for h in history if "train_action_mse" in h or "val_action_mse" in h]
    if evals:
        out["action_mse_first"], out["action_mse_last"] = (
            evals[0].get("val_action_mse", evals[0].get("train_action_mse")),
            evals[-1].get("val_action_mse", evals[-1].get("train_action_mse")),
        )
    out["check"] = collect(run_dir, check.out or check.work / "returned")
    return out


def summarize(results: dict) -> dict:
    """The headline figures, lifted from the parts (None where a part did not measure them)."""
    parts = results["parts"]
    summary: dict = {
        "paper_p99_goal_ms": PAPER_P99_GOAL_MS,
        "rtc_goal": RTC_GOAL,
        "gpu_busy_goal_pct": GPU_BUSY_GOAL_PCT,
    }
    graph_diffs = []
    for role in ("paper", "compact"):
        part = parts.get(f"policy_{role}", {})
        modes = dict(part.get("result", {}).get("modes", {}))
        fallback = part.get("fallback", {}).get("result", {}).get("modes", {})
        modes.update(fallback)
        measured = {m: r for m, r in modes.items() if "ddim16_p99_ms" in r}
        best = min(measured, key=lambda m: measured[m]["ddim16_p99_ms"]) if measured else None
        summary[f"{role}_preset"] = part.get("result", {}).get("preset")
        summary[f"{role}_ddim16_p99_ms"] = measured[best]["ddim16_p99_ms"] if best else None
        summary[f"{role}_ddim16_median_ms"] = measured[best]["ddim16_median_ms"] if best else None
        summary[f"{role}_best_mode"] = best
        summary[f"{role}_rtc_vs_plain"] = measured[best].get("rtc_vs_plain") if best else None
        summary[f"{role}_modes_p99_ms"] = {m: r["ddim16_p99_ms"] for m, r in measured.items()}
        graph_diffs += [
            r[k]
            for r in measured.values()
            for k in ("max_abs_diff_vs_ungraphed", "rtc_max_abs_diff_vs_ungraphed")
            if k in r
        ]
    p99 = summary["paper_ddim16_p99_ms"]
    summary["paper_p99_goal_met"] = None if p99 is None or results["rehearsal"] else p99 <= PAPER_P99_GOAL_MS
    summary["graph_max_abs_diff"] = max(graph_diffs) if graph_diffs else None
    throughput, busy, waits = {}, {}, {}
    for name, part in parts.items():
        res = part.get("result") or {}
        if not name.startswith("train_bench_") or "preset" not in res:
            continue
        device = "cuda" if res.get("cuda") else "cpu"
        for run in res.get(f"{device}_runs") or [res[device]]:
            key = f"{res['preset']}/{res['policy']}/{run['precision']}/{run['data']}"
            throughput[key] = run.get("samples_per_s", run.get("error"))
            waits[key] = run.get("data_wait_share")
            busy[key] = run.get("gpu_busy_pct")
    summary["train_samples_per_s"] = throughput
    summary["train_data_wait_share"] = waits
    summary["train_gpu_busy_pct"] = busy
    training = parts.get("training", {})
    summary["training_loss_fell"] = training.get("loss_fell")
    summary["training_checkpoint_loads_on_cpu"] = training.get("check", {}).get("loads_on_cpu")
    ddp = parts.get("ddp", {}).get("check", {})
    summary["ddp_backend"] = ddp.get("backend")
    summary["ddp_result_loads"] = ddp.get("loads_on_cpu")
    summary["parts_ok"] = sorted(n for n, p in parts.items() if p.get("status") == "ok")
    summary["parts_failed"] = sorted(n for n, p in parts.items() if p.get("status") in ("error", "timeout"))
    summary["parts_skipped"] = sorted(n for n, p in parts.items() if p.get("status") == "skipped")
    return summary


def environment(check: Check) -> dict:
    env = {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()}
    try:
        from equidiff_core.runtime.machine import cpu_model

        env["cpu"] = f"{cpu_model()}, {os.cpu_count()} cores"
    except ImportError:
        pass
    commit = CARRY / "commit.txt"
    if commit.is_file():
        env["commit"] = commit.read_text().strip()
    try:
        import torch

        env.update(torch=torch.__version__, cuda=torch.version.cuda, cuda_available=torch.cuda.is_available())
        if torch.cuda.is_available():
            props = torch.cuda.get_device_properties(0)
            env.update(
                gpu=props.name,
                gpu_memory_gb=round(props.total_memory / 1e9, 1),
                multiprocessors=props.multi_processor_count,
                cudnn=torch.backends.cudnn.version(),
            )
        for name in ("numpy", "scipy", "escnn", "diffusers", "lie_learn", "py3nj"):
            try:
                env[name] = package_version(name)
            except PackageNotFoundError:
                env[name] = None
    except ImportError as err:
        env["torch"] = f"missing: {err}"
    if shutil.which("nvidia-smi"):
        smi = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,clocks.sm,temperature.gpu", "--format=csv,noheader"],
            capture_output=True,
            text=True,
        )
        env["nvidia_smi"] = smi.stdout.strip()
    return env


def parse_plan(check: Check) -> dict[str, str]:
    """Every part's ``equidiff`` arguments parsed by the CLI's own parser, nothing run: the typo
    that would cost a GPU minute shows here in a second. Part name -> argparse's error ('' when fine)."""
    from equidiff_ros.cli import build_parser  # the repository's own code: imported only where it runs

    parts = [p for part in plan(check) for p in (part, part.fallback) if p is not None]
    problems = {}
    for part in parts:
        args = part.argv[part.argv.index("equidiff_ros.cli") + 1 :]
        stderr = io.StringIO()
        try:
            with contextlib.redirect_stderr(stderr):
                build_parser(args).parse_args(args)
            problems[part.name] = ""
        except SystemExit:
            problems[part.name] = stderr.getvalue().strip().splitlines()[-1]
    return problems


def cmd_run(args) -> int:
    check = Check(args)
    if args.dry_run:
        problems = parse_plan(check)
        print(json.dumps({"device": check.device, "sizes": check.results["sizes"], "parts": problems}))
        return 1 if any(problems.values()) else 0
    check.work.mkdir(parents=True, exist_ok=True)
    check.log_path.write_text("")
    for stale in ("ddp", "train", "returned"):  # a rerun on a warm machine starts clean
        shutil.rmtree(check.work / stale, ignore_errors=True)
    env = environment(check)
    check.results["env"] = env
    check.results["gpu"] = env.get("gpu")
    if args.device == "cuda" and not env.get("cuda_available"):
        check.results["error"] = f"CUDA not available (torch {env.get('torch')}): nothing measured"
        check.save()
        print(check.results["error"], file=sys.stderr)
        return 2
    if not check.packed.is_dir() or not any(check.packed.glob("*.episode.npz")):
        check.results["error"] = (
            f"no packed episodes in {check.packed}: run scripts/gpu_prepare.sh and carry .gpu_carry"
        )
        check.save()
        print(check.results["error"], file=sys.stderr)
        return 2
    check.save()
    for part in plan(check):
        print(f"[gpu_check] {part.name} ({check.left_s():.0f} s of the budget left)", flush=True)
        check.results["parts"][part.name] = run_part(check, part)
        check.save()
    print(table(check.results), flush=True)
    print(f"[gpu_check] wrote {check.json_path}" + (f" and {check.out}/gpu_check.json" if check.out else ""))
    return 0 if not check.results["parts_failed"] else 1


def table(results: dict) -> str:
    rows = [f"{'part':36} {'status':8} {'s':>6}"]
    for name, part in results["parts"].items():
        rows.append(
            f"{name:36} {part.get('status', '?'):8} {part.get('seconds', 0):6.1f}  {part.get('error', part.get('reason', ''))[:90]}"
        )
    keys = (
        "gpu",
        "paper_preset",
        "paper_ddim16_p99_ms",
        "paper_best_mode",
        "paper_rtc_vs_plain",
        "compact_ddim16_p99_ms",
        "graph_max_abs_diff",
        "training_loss_fell",
        "training_checkpoint_loads_on_cpu",
        "ddp_backend",
        "ddp_result_loads",
    )
    rows += [f"{k}: {results.get(k)}" for k in keys]
    rows.append(f"train_samples_per_s: {json.dumps(results.get('train_samples_per_s'))}")
    rows.append(f"train_gpu_busy_pct: {json.dumps(results.get('train_gpu_busy_pct'))}")
    return "\n".join(rows)


# ----- subcommands that load models (torch and the project imported here, not at module level) -----


def collect(run_dir: Path, dest: Path) -> dict:
    """Copy a training run's files to ``dest`` under the names that come back from $OUT, then verify them."""
    from equidiff_core.training.loop import without_optimizer_state

    dest.mkdir(parents=True, exist_ok=True)
    without_optimizer_state(run_dir / "last.ckpt", dest / "train_last.ckpt")
    for src, name in (
        ("policy.pt", "train_policy.pt"),
        ("history.json", "train_history.json"),
        ("training.png", "training.png"),
    ):
        if (run_dir / src).is_file():
            shutil.copyfile(run_dir / src, dest / name)
    too_big = [p.name for p in dest.iterdir() if p.stat().st_size > OUT_FILE_LIMIT]
    return {**verify(dest), "too_big_to_return": too_big}


def cmd_collect(args) -> int:
    print(json.dumps(collect(Path(args.run_dir), Path(args.dest))))
    return 0


def verify(directory: Path) -> dict:
    """The GPU-trained files load on this CPU: the exported policy predicts finite actions, the
    checkpoint rebuilds the training-time policy (escnn for EquiDiff), which predicts too."""
    import numpy as np
    import torch

    from equidiff_core.benches.timing import probe_observation
    from equidiff_core.policy.inference import load_inference_policy
    from equidiff_core.training.loop import load_policy_from_checkpoint, load_training_checkpoint

    policy = load_inference_policy(directory / "train_policy.pt", device="cpu")
    vox, ee = probe_observation(policy.preset, policy.workspace)
    actions = policy.predict(vox, ee, seed=0)
    restored = load_policy_from_checkpoint(directory / "train_last.ckpt", "cpu").eval()
    obs = {"voxels": torch.from_numpy(vox)[None, None], "ee": torch.from_numpy(ee)[None, None]}
    with torch.no_grad():
        again = restored.predict_action(obs, noise=torch.zeros(1, policy.preset.horizon, restored.codec.dim))
    state = load_training_checkpoint(directory / "train_last.ckpt")
    return {
        "loads_on_cpu": bool(np.isfinite(actions).all() and torch.isfinite(again["action_pred"]).all()),
        "preset": policy.preset.name,
        "policy": policy.name,
        "checkpoint_step": int(state["step"]),
        "train_config": {
            k: state.get("train_config", {}).get(k) for k in ("device", "precision", "data", "batch_size")
        },
    }


def cmd_verify(args) -> int:
    print(json.dumps(verify(Path(args.dir))))
    return 0


def check_ddp(run_dir: Path) -> dict:
    """A torchrun run's checkpoint: one sync row (world size, backend, equal digests), and the
    weights loaded on the CPU hash to rank 0's digest."""
    import numpy as np

    from equidiff_core.benches.timing import probe_observation
    from equidiff_core.policy.inference import load_inference_policy
    from equidiff_core.training import distributed
    from equidiff_core.training.loop import load_policy_from_checkpoint

    history = json.loads((run_dir / "history.json").read_text())
    sync = next(h for h in history if "param_digests" in h)
    restored = load_policy_from_checkpoint(run_dir / "last.ckpt", "cpu")
    policy = load_inference_policy(run_dir / "policy.pt", device="cpu")
    vox, ee = probe_observation(policy.preset, policy.workspace)
    return {
        "world_size": sync["world_size"],
        "backend": sync.get("backend"),
        "ranks_agree": len(set(sync["param_digests"])) == 1,
        "loads_on_cpu": distributed.parameter_digest(restored.model) == sync["param_digests"][0]
        and bool(np.isfinite(policy.predict(vox, ee, seed=0)).all()),
        "steps": max(h["step"] for h in history if "loss" in h),
    }


def cmd_check_ddp(args) -> int:
    print(json.dumps(check_ddp(Path(args.run_dir))))
    return 0


def cmd_size(args) -> int:
    """Bytes a device call would send: tracked and untracked-not-ignored files, plus the carried paths."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout.decode()
    files = [ROOT / p for p in listed.split("\0") if p and (ROOT / p).is_file()]
    by_top: dict[str, int] = {}
    for f in files:
        top = f.relative_to(ROOT).parts[0]
        by_top[top] = by_top.get(top, 0) + f.stat().st_size
    carried = {}
    for c in args.carry:
        path = ROOT / c
        carried[c] = sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.exists() else 0
    tree, carry = sum(by_top.values()), sum(carried.values())
    result = {
        "tree_mib": round(tree / 2**20, 2),
        "carry_mib": {k: round(v / 2**20, 2) for k, v in carried.items()},
        "total_mib": round((tree + carry) / 2**20, 2),
        "limit_mib": DEVICE_TREE_LIMIT / 2**20,
        "fits": tree + carry <= DEVICE_TREE_LIMIT,
        "largest": {k: round(v / 2**20, 2) for k, v in sorted(by_top.items(), key=lambda kv: -kv[1])[:6]},
    }
    print(json.dumps(result))
    return 0 if result["fits"] else 3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="the check (what scripts/gpu_check.sh runs)")
    run.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    run.add_argument("--tiny", action="store_true", help="tiny sizes (implied by --device cpu)")
    run.add_argument(
        "--budget-s", type=float, default=None, help="wall-clock budget for all parts (default 450 s on CUDA)"
    )
    run.add_argument(
        "--json", help="the result file (default docs/results/gpu_check.json on CUDA, WORK/gpu_check.json on the CPU)"
    )
    run.add_argument("--work", default="/tmp/equidiff_gpu_check", help="scratch directory (runs, caches, log)")
    run.add_argument("--packed", help="packed episodes to train on (default .gpu_carry/packed)")
    run.add_argument(
        "--dry-run", action="store_true", help="parse every part's equidiff command with the CLI's parser, run nothing"
    )
    run.set_defaults(func=cmd_run)
    collect = sub.add_parser("collect", help="copy a training run's files under their returned names and verify them")
    collect.add_argument("run_dir")
    collect.add_argument("dest")
    collect.set_defaults(func=cmd_collect)
    ver = sub.add_parser("verify", help="the returned train_policy.pt / train_last.ckpt load and predict on this CPU")
    ver.add_argument("dir")
    ver.set_defaults(func=cmd_verify)
    ddp = sub.add_parser("check-ddp", help="a torchrun run's digests agree and its checkpoint loads on the CPU")
    ddp.add_argument("run_dir")
    ddp.set_defaults(func=cmd_check_ddp)
    size = sub.add_parser("size", help="what a device call would send, against its 64 MiB limit")
    size.add_argument("--carry", nargs="*", default=[".gpu_carry"])
    size.set_defaults(func=cmd_size)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
