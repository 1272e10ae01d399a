"""Bag integrity: bags carry real MCAP CRCs, every read checks them, a flipped bit is reported with
its episode, topic and time, repair keeps the intact chunks, CRC-less bags read as "unchecked";
and a fuzz of the reader with flipped and truncated bytes (no ROS needed)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from helpers_data import SyntheticEpisode, write_synthetic_episode
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from equidiff_core.data.bags import EpisodeMeta, read_episode, repair_bag, scan_mcap, verify_bag
from equidiff_core.data.dataset import dataset_stats
from equidiff_core.data.mcap_reader import CHECKED, UNCHECKED, BagError, BagIntegrityError
from equidiff_core.data.mcap_writer import open_bag_writer
from equidiff_core.data.recording import RecordingConfig
from equidiff_core.wire.rosmsg import rosbags_factory

CFG = RecordingConfig(min_free_gib=0.0, chunk_size_mib=2.0)
F = rosbags_factory()


def chunk_records(mcap: Path) -> list:
    """The chunk records of an .mcap as the ``mcap`` package's stream reader sees them."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with open(mcap, "rb") as fh:
        return [r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk)]


def flip_bit_in_chunk(mcap: Path, chunk_index: int) -> int:
    """Flip one bit in the middle of the data of the ``chunk_index``-th chunk; returns the chunk's first log time."""
    chunk = chunk_records(mcap)[chunk_index]
    data = bytearray(mcap.read_bytes())
    at = data.find(chunk.data)
    assert at > 0
    data[at + len(chunk.data) // 2] ^= 0x10
    mcap.write_bytes(bytes(data))
    return chunk.message_start_time


@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> Path:
    """A recorder-written synthetic episode in several chunks."""
    return write_synthetic_episode(
        tmp_path_factory.mktemp("integrity") / "ep", SyntheticEpisode(duration_s=6.0), config=CFG
    )


def test_recorded_bags_carry_crcs_that_independent_readers_check(episode):
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    mcap = episode / "ep.mcap"
    chunks = chunk_records(mcap)
    assert len(chunks) >= 2 and all(c.uncompressed_crc != 0 for c in chunks)
    with open(mcap, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        n_mcap = sum(1 for _ in reader.iter_messages())
    with Reader(episode) as reader:  # rosbags (what rosbag2's layout promises) opens it too
        n_rosbags = sum(1 for _ in reader.messages())
    ep = read_episode(episode)
    assert ep.integrity == CHECKED
    assert n_mcap == n_rosbags == sum(ep.message_counts.values())
    assert verify_bag(episode).integrity == CHECKED


def test_a_flipped_bit_names_episode_topic_and_time_and_is_refused_by_stats(episode, tmp_path):
    bad = tmp_path / "ep"
    shutil.copytree(episode, bad)
    start_ns = flip_bit_in_chunk(bad / "ep.mcap", 1)
    with pytest.raises(BagIntegrityError) as caught:
        read_episode(bad, topics=["/voxels"])  # a topic filter still checks the whole file
    msg = str(caught.value)
    assert str(bad) in msg and "CRC mismatch" in msg and "/voxels" in msg
    assert f"{start_ns // 1_000_000_000}.{start_ns % 1_000_000_000:09d} s" in msg  # the first message's time
    assert "equidiff bags repair" in msg
    [damaged] = caught.value.damaged
    assert damaged.start_ns == start_ns and damaged.total > 0 and damaged.first_topic
    stats = dataset_stats([episode, bad])
    assert stats["total"]["episodes"] == 1 and stats["total"]["skipped"] == 1
    assert "CRC mismatch" in stats["skipped"][0]["reason"]
    assert stats["episodes"][0]["integrity"] == CHECKED and stats["total"]["unchecked"] == 0


def test_repair_keeps_the_intact_chunks_and_says_what_it_dropped(episode, tmp_path, capsys):
    from equidiff_ros.cli import main as cli

    bad = tmp_path / "ep"
    shutil.copytree(episode, bad)
    flip_bit_in_chunk(bad / "ep.mcap", 1)
    full = read_episode(episode)
    assert cli(["bags", "repair", str(bad)]) == 0
    out = capsys.readouterr().out
    assert f"repaired {bad}" in out and "dropped chunk at byte" in out and "CRC mismatch" in out
    got = read_episode(bad)
    assert got.integrity == CHECKED and "damaged chunks dropped" in got.meta.notes
    lost = sum(full.message_counts.values()) - sum(got.message_counts.values())
    assert lost > 0
    # every kept message is the original's at the same log time, byte for byte
    for topic, msgs in got.topics.items():
        original = dict(zip(full[topic].log_ns.tolist(), full[topic].messages))
        for t, m in zip(msgs.log_ns.tolist(), msgs.messages):
            assert F.typestore.serialize_cdr(m, msgs.msgtype) == F.typestore.serialize_cdr(original[t], msgs.msgtype)
    # the report's counts are the messages lost
    report_dir = tmp_path / "again"
    shutil.copytree(bad.with_name("ep.unrepaired"), report_dir)
    (report_dir / "ep.mcap").rename(report_dir / "again.mcap")
    report = repair_bag(report_dir, output=tmp_path / "fixed")
    assert sum(d.total for d in report.damaged) == lost
    assert any("/voxels" in line for line in report.dropped())


def test_a_bag_without_crcs_reads_but_is_reported_unchecked(episode, tmp_path):
    """rosbags' stock MCAP storage (the project's bags before) writes CRC 0 everywhere."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    old = tmp_path / "old"
    with Reader(episode) as reader, Writer(old, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            c.id: writer.add_connection(
                c.topic,
                c.msgtype,
                msgdef=c.msgdef.data,
                rihs01=c.digest,
                offered_qos_profiles=c.ext.offered_qos_profiles,
            )
            for c in reader.connections
        }
        for conn, ts, raw in reader.messages():
            writer.write(conns[conn.id], ts, raw)
        for key, value in EpisodeMeta(task="pick_cube", success=True).to_custom_data().items():
            writer.set_custom_data(key, value)
    assert all(c.uncompressed_crc == 0 for c in chunk_records(old / "old.mcap"))
    ep = read_episode(old)
    assert ep.integrity == UNCHECKED and ep.message_counts == read_episode(episode).message_counts
    stats = dataset_stats([episode, old])
    assert stats["total"]["episodes"] == 2 and stats["total"]["unchecked"] == 1
    assert [r["integrity"] for r in stats["episodes"]] == [CHECKED, UNCHECKED]


# --- fuzz: flipped and truncated bytes ---------------------------------------------------------

TOPICS = {"/a": "std_msgs/msg/String", "/b": "geometry_msgs/msg/PointStamped"}


def _small_bag(path: Path) -> list[tuple[str, int, bytes]]:
    """A bag of a few messages on two topics in several small chunks; its (topic, log_ns, CDR) in order."""
    writer = open_bag_writer(path, chunk_size=120, chunk_max_age_s=float("inf"))
    conns = {t: writer.add_connection(t, ty, typestore=F.typestore) for t, ty in TOPICS.items()}
    written = []
    for i in range(8):
        t = 1_000 + 10 * i
        if i % 2:
            msg = F.make(
                "geometry_msgs/msg/PointStamped",
                header=F.header(t, "base"),
                point=F.make("geometry_msgs/msg/Point", x=i * 0.5, y=-1.0, z=2.0 + i),
            )
            topic = "/b"
        else:
            msg, topic = F.make("std_msgs/msg/String", data=f"message {i}"), "/a"
        data = F.typestore.serialize_cdr(msg, TOPICS[topic])
        writer.write(conns[topic], t, data)
        written.append((topic, t, bytes(data)))
    writer.close()
    return written


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz") / "small"
    written = _small_bag(path)
    assert len(chunk_records(path / "small.mcap")) >= 3  # flips land in chunks, indexes and the summary alike
    return path, written, (path / "small.mcap").read_bytes()


def _messages(episode) -> list[tuple[str, int, bytes]]:
    out = [
        (topic, int(t), bytes(F.typestore.serialize_cdr(m, msgs.msgtype)))
        for topic, msgs in episode.topics.items()
        for t, m in zip(msgs.log_ns, msgs.messages)
    ]
    return sorted(out, key=lambda x: (x[1], x[0]))


def _mutated_copy(small_bag, mutate) -> Path:
    path, _, data = small_bag
    tmp = Path(tempfile.mkdtemp(prefix="fuzz_bag_"))
    bag = tmp / "small"
    bag.mkdir()
    shutil.copy(path / "metadata.yaml", bag / "metadata.yaml")
    (bag / "small.mcap").write_bytes(mutate(bytearray(data)))
    return bag


FUZZ = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@FUZZ
@given(data=st.data())
def test_fuzz_reader_returns_the_exact_messages_or_a_documented_error(small_bag, data):
    _, written, raw = small_bag
    n_flips = data.draw(st.integers(0, 3))
    spots = data.draw(
        st.lists(st.tuples(st.integers(0, len(raw) - 1), st.integers(0, 7)), min_size=n_flips, max_size=n_flips)
    )
    cut = data.draw(st.one_of(st.none(), st.integers(0, len(raw) - 1)))

    def mutate(buf: bytearray) -> bytes:
        for at, bit in spots:
            buf[at] ^= 1 << bit
        return bytes(buf[:cut] if cut is not None else buf)

    bag = _mutated_copy(small_bag, mutate)
    try:
        try:
            episode = read_episode(bag)
        except BagError as err:  # BagIntegrityError is one: a documented error, with a message naming the problem
            assert str(bag) in str(err) and len(str(err)) > len(str(bag)) + 10
            return
        assert _messages(episode) == sorted(written, key=lambda x: (x[1], x[0]))  # never a silently changed message
        if not spots and cut is None:
            assert episode.integrity == CHECKED
    finally:
        shutil.rmtree(bag.parent)


@FUZZ
@given(data=st.data())
def test_fuzz_repair_scan_keeps_only_exact_messages(small_bag, data):
    """The tolerant scan behind ``bags repair``: whatever it keeps is an original message, unchanged."""
    _, written, raw = small_bag
    spots = data.draw(st.lists(st.tuples(st.integers(0, len(raw) - 1), st.integers(0, 7)), max_size=3))
    cut = data.draw(st.one_of(st.none(), st.integers(8, len(raw) - 1)))

    def mutate(buf: bytearray) -> bytes:
        for at, bit in spots:
            if at >= 8:  # keep the magic: a file that is not MCAP at all is refused outright (tested above)
                buf[at] ^= 1 << bit
        return bytes(buf[:cut] if cut is not None else buf)

    bag = _mutated_copy(small_bag, mutate)
    try:
        try:
            salvage = scan_mcap(bag / "small.mcap")
        except BagError as err:
            # a damaged record outside every chunk (a schema or channel the messages need) leaves nothing
            # to salvage: refused with our documented error and its reason, never a silently changed message
            assert str(err)
            return
        kept = [(ch.topic, t, bytes(d)) for ch, t, d in salvage.messages]
        assert set(kept) <= set(written)
        assert kept == [m for m in written if m in set(kept)]  # in the original order
        if not spots and cut is None:
            assert kept == written and salvage.complete and not salvage.damaged
    finally:
        shutil.rmtree(bag.parent)


def test_the_shipped_sample_bag_carries_crcs():
    """Re-written by scripts/rewrite_integrity.py (its --check mode verifies every shipped file)."""
    root = Path(__file__).resolve().parents[1]
    [bag] = [b for b in (root / "bags").iterdir() if b.is_dir()]
    assert verify_bag(bag).integrity == CHECKED
