"""Re-write the shipped policy files, training checkpoints and sample bag in the integrity-checked form.

    PYTHONPATH=src python scripts/rewrite_integrity.py            # rewrite what lacks it, verify all
    PYTHONPATH=src python scripts/rewrite_integrity.py --check    # verify only (exit 1 if any is old)

* ``checkpoints/**/policy.pt`` (exported policies) and ``checkpoints/**/*.ckpt`` (training
  checkpoints) get the sha256 of their weights (``policy.file.rewrite_with_hash``). Verified:
  the same tensors bit for bit, and an exported policy predicts the same actions (same seed).
* ``bags/*`` (the sample episode) is re-written through the project's bag writer (chunk,
  data-section and summary CRCs). Verified: the same messages (topic, log time, bytes) in the
  same order, the same metadata, and every CRC checks.

Safe to re-run: files already in the new form are only verified. Nothing is replaced before its
rewritten copy has been verified.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from rosbags.rosbag2.storage_mcap import parse_qos

from equidiff_core.data.bags import find_bags, read_meta, scan_mcap, verify_bag
from equidiff_core.data.mcap_reader import CHECKED
from equidiff_core.data.mcap_writer import open_bag_writer
from equidiff_core.policy.file import FORMAT, HASH_KEY, rewrite_with_hash
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.wire.rosmsg import rosbags_factory

ROOT = Path(__file__).resolve().parents[1]
CKPT_FORMAT = "equidiff_train_ckpt"


def _prediction(path: Path) -> np.ndarray:
    policy = load_inference_policy(path)
    res = policy.workspace.resolution
    voxels = np.zeros((4, res, res, res), np.uint8)
    voxels[:, res // 2 - 3 : res // 2 + 3, res // 2 - 3 : res // 2 + 3, 2:8] = 200
    ee = np.array([0.45, 0.0, 0.2, 1, 0, 0, 0, 1, 0, 0.04], np.float32)
    return policy.predict(voxels, ee, seed=0)


def upgrade_torch_file(path: Path, check_only: bool) -> str:
    payload = torch.load(path, map_location="cpu", weights_only=True)
    fmt = payload.get("format") if isinstance(payload, dict) else None
    if fmt not in (FORMAT, CKPT_FORMAT):
        return f"skipped {path}: not a policy file or training checkpoint (format {fmt!r})"
    key = "state_dict" if fmt == FORMAT else "model"
    if payload.get(HASH_KEY):
        if fmt == FORMAT:
            load_inference_policy(path)  # checks the hash
        return f"ok {path}: sha256 {payload[HASH_KEY][:16]}..."
    if check_only:
        raise SystemExit(f"{path}: no weights hash yet (run without --check)")
    with tempfile.TemporaryDirectory() as tmp:
        new = Path(tmp) / path.name
        digest = rewrite_with_hash(path, new, weights_key=key)
        again = torch.load(new, map_location="cpu", weights_only=True)
        old_w, new_w = payload[key], again[key]
        assert old_w.keys() == new_w.keys() and all(torch.equal(old_w[k], new_w[k]) for k in old_w), path
        assert {k for k in again if k != HASH_KEY} == set(payload), path
        if fmt == FORMAT:
            assert np.array_equal(_prediction(path), _prediction(new)), f"{path}: predictions differ"
        shutil.move(new, path)
    same = "weights and predictions identical" if fmt == FORMAT else "weights identical"
    return f"rewrote {path}: sha256 {digest[:16]}... ({same})"


def upgrade_bag(bag: Path, check_only: bool) -> str:
    if verify_bag(bag).integrity == CHECKED:
        return f"ok {bag}: every CRC checks"
    if check_only:
        raise SystemExit(f"{bag}: written without CRCs (run without --check)")
    mcap = next(bag.glob("*.mcap"))
    old = scan_mcap(mcap)
    assert old.complete and not old.damaged, f"{bag}: damaged; repair it first"
    original = [(ch.topic, ch.msgtype, t, bytes(d)) for ch, t, d in old.messages]
    with tempfile.TemporaryDirectory(dir=bag.parent) as tmp:
        new = Path(tmp) / bag.name
        writer = open_bag_writer(new, chunk_max_age_s=float("inf"))
        try:
            conns = {}
            for ch in sorted({ch.id: ch for ch, _, _ in old.messages}.values(), key=lambda ch: ch.id):
                qos = ch.metadata.get("offered_qos_profiles", "")
                conns[ch.id] = writer.add_connection(
                    ch.topic,
                    ch.msgtype,
                    msgdef=ch.schema_text,
                    rihs01=rosbags_factory().typestore.hash_rihs01(ch.msgtype),
                    serialization_format=ch.message_encoding,
                    offered_qos_profiles=parse_qos(qos) if qos else [],
                )
            for ch, t, d in old.messages:
                writer.write(conns[ch.id], t, d)
            for key, value in read_meta(bag).to_custom_data().items():
                writer.set_custom_data(key, value)
            writer.close()
        except BaseException:
            writer.abort()
            raise
        for extra in bag.iterdir():  # the sidecar and anything else beside the bag
            if extra.suffix != ".mcap" and extra.name != "metadata.yaml":
                shutil.copy2(extra, new / extra.name)
        scan = verify_bag(new)
        rewritten = [(ch.topic, ch.msgtype, t, bytes(d)) for ch, t, d in scan_mcap(next(new.glob("*.mcap"))).messages]
        assert scan.integrity == CHECKED and rewritten == original, f"{bag}: messages differ after rewriting"
        assert read_meta(new) == read_meta(bag), f"{bag}: metadata differs after rewriting"
        backup = Path(tmp) / f"{bag.name}.old"
        bag.rename(backup)
        new.rename(bag)
    return f"rewrote {bag}: {len(original)} messages identical, every CRC checks"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="verify only; exit 1 if a file is in the old form")
    args = parser.parse_args(argv)
    files = sorted(p for pattern in ("policy.pt", "*.ckpt") for p in (ROOT / "checkpoints").rglob(pattern))
    try:
        for path in files:
            print(upgrade_torch_file(path, args.check), flush=True)
        for bag in find_bags([ROOT / "bags"]):
            print(upgrade_bag(bag, args.check), flush=True)
    except SystemExit as err:
        print(err, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
