"""The approximate-time matcher behind voxel_node: slop, freshest set, hand-out-once, staleness."""

import pytest

from equidiff_core.perception.sync import ApproximateTimeMatcher

MS = 1_000_000
NAMES = ("a", "b", "c")


def _feed(m, name, stamps_ms):
    for s in stamps_ms:
        m.add(name, s * MS, f"{name}{s}")


def test_freshest_complete_set_within_slop():
    m = ApproximateTimeMatcher(NAMES, slop_ns=30 * MS)
    _feed(m, "a", [0, 200, 400])
    _feed(m, "b", [10, 210, 410])
    _feed(m, "c", [20, 220])  # c has not delivered its 4xx frame yet
    match = m.newest()
    assert match.items == {"a": "a200", "b": "b210", "c": "c220"}
    assert match.newest_ns == 220 * MS and match.oldest_ns == 200 * MS and match.spread_ns == 20 * MS
    _feed(m, "c", [405])
    assert m.newest().items == {"a": "a400", "b": "b410", "c": "c405"}


def test_slop_is_respected():
    strict = ApproximateTimeMatcher(NAMES, slop_ns=25 * MS)
    loose = ApproximateTimeMatcher(NAMES, slop_ns=35 * MS)
    for m in (strict, loose):
        _feed(m, "a", [100])
        _feed(m, "b", [115])
        _feed(m, "c", [130])
    assert strict.newest() is None
    assert loose.newest().items == {"a": "a100", "b": "b115", "c": "c130"}


def test_a_missing_stream_blocks_matching():
    m = ApproximateTimeMatcher(NAMES, slop_ns=50 * MS)
    _feed(m, "a", [0, 200])
    _feed(m, "b", [0, 200])
    assert m.newest() is None and m.peek() is None


def test_each_match_is_handed_out_once_and_only_newer_data_follows():
    m = ApproximateTimeMatcher(NAMES, slop_ns=30 * MS)
    for n in NAMES:
        _feed(m, n, [100])
    assert m.newest() is not None
    assert m.newest() is None  # nothing new
    assert m.peek() is not None  # but it is still the freshest set
    _feed(m, "a", [300])  # only one stream moved on: no new complete set
    assert m.newest() is None
    _feed(m, "b", [310])
    _feed(m, "c", [290])
    assert m.newest().items == {"a": "a300", "b": "b310", "c": "c290"}


def test_out_of_order_items_are_slotted_by_stamp_and_queue_is_bounded():
    m = ApproximateTimeMatcher(("a", "b"), slop_ns=5 * MS, queue_size=3)
    _feed(m, "a", [100, 300, 200])
    _feed(m, "b", [201])
    assert m.newest().items == {"a": "a200", "b": "b201"}
    _feed(m, "a", [400, 500, 600])  # pushes 100..300 out
    _feed(m, "b", [199])
    assert m.peek() is None  # a's 200 is gone, so b's stray 199 has no partner
    assert m.latest_stamp("a") == 600 * MS


def test_staleness_and_ages():
    m = ApproximateTimeMatcher(NAMES, slop_ns=30 * MS)
    now = 1_000 * MS
    assert m.stale(now, 500 * MS) == ["a", "b", "c"]  # nothing received yet
    _feed(m, "a", [900])
    _feed(m, "b", [300])
    assert m.ages_ns(now) == {"a": 100 * MS, "b": 700 * MS, "c": None}
    assert m.stale(now, 500 * MS) == ["b", "c"]


def test_invalid_construction_and_unknown_stream():
    with pytest.raises(ValueError, match="unique"):
        ApproximateTimeMatcher(["a", "a"], 1)
    with pytest.raises(ValueError, match="slop"):
        ApproximateTimeMatcher(["a"], -1)
    with pytest.raises(ValueError, match="at least one"):
        ApproximateTimeMatcher([], 1)
    m = ApproximateTimeMatcher(["a"], 1)
    with pytest.raises(KeyError, match="unknown stream 'z'"):
        m.add("z", 0, None)


def test_publish_pacer_picks_frames_near_the_clock_grid_whatever_the_start_phase():
    from equidiff_core.perception.sync import PublishPacer

    # two 30 fps cameras started at different phases, published at 5 Hz
    picked = []
    for offset in (0.0123, 0.0291):
        pacer = PublishPacer(5.0)
        times = [100.0 + offset + i / 30 for i in range(90)]  # 3 s
        picked.append([t for t in times if pacer.due(t)])
    assert all(14 <= len(p) <= 16 for p in picked)  # 5 Hz over 3 s
    for a, b in zip(*picked):
        assert abs(a - b) <= 1 / 30 + 1e-9  # frames of the same tick: within one device frame
    assert all(0.15 < b - a < 0.25 for a, b in zip(picked[0], picked[0][1:]))
    # a source that already delivers at 5 Hz gets every frame through, whatever its phase
    for phase in (0.0, 0.07, 0.16, 0.199):
        pacer = PublishPacer(5.0)
        assert all(pacer.due(50.0 + phase + i * 0.2 + (0.01 if i % 3 == 0 else 0.0)) for i in range(20))


def test_on_demand_source_read_at_the_pacers_times_lands_on_the_grid():
    from equidiff_core.perception.sync import PublishPacer

    pacer = PublishPacer(5.0)
    now, published = 10.037, []
    for _ in range(10):
        now += pacer.wait_s(now)
        render = 0.04  # the frame is captured at `now`, ready 40 ms later
        if pacer.due(now):
            published.append(now)
        now += render
    assert len(published) == 10
    assert all(abs(t / 0.2 - round(t / 0.2)) < 1e-6 for t in published[1:])  # on the 0.2 s grid
