"""The NRT pipe: messages, the two ends, and peers in a thread or a subprocess.

The fast end must never block, whatever the NRT side does (slow, stalled, flooding, dead).
A blocking call would last as long as the NRT side stalls (a second or more here), so each
call's duration is checked against 100 ms, and all but a few host stalls against 5 ms: a
loose sanity bound, not a benchmark.
"""

from __future__ import annotations

import asyncio
import math
import os
import resource
import signal
import socket
import struct
import sys
import threading
import time

import pytest
from conftest import NOT_HUNG_S, require_root
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.pipe import (
    HEADER,
    MAGIC,
    MAX_MESSAGE,
    VERSION,
    FastEnd,
    MalformedMessage,
    Message,
    MessageDefinitionError,
    NrtEnd,
    NrtPeer,
    PeerGone,
    PipeError,
    PipeTimeout,
    codec,
    pipe_pair,
)


class Grip(Message):
    TYPE = 201
    FIELDS = (("grasp", "d"), ("speed", "d"), ("force", "d"), ("object", "?"), ("fault", "H"))


class Mixed(Message):
    TYPE = 202
    FIELDS = tuple((f"v{i}", code) for i, code in enumerate("bBhHiIlLqQefd?"))


class Beat(Message):
    TYPE = 203


CALL_BOUND_S = 0.005  # the median fast-side call: a loose sanity bound
BLOCKED_S = 0.1  # no call may come near the NRT side's stall (>= 1 s): that would be blocking


def assert_never_blocked(timed: Timed, host_stalls: int = 0) -> None:
    """Calls are fast, and none took long while sleeping in the kernel. A voluntary context
    switch alone is not blocking (waiting for the GIL held by an NRT thread is one, and brief);
    a long call without one is the VM being stalled, not the pipe. ``host_stalls``: long calls
    tolerated where the test proves otherwise that the pipe did not block (a GIL wait that a
    stall of the whole VM stretched: CI saw 252 ms)."""
    durations = sorted(timed.durations)
    assert durations, "no call was timed"
    # typical calls are fast; single long ones without a sleep are the host preempting this
    # thread (seen: 6 of 100 calls at 12-230 ms while the host took CPU), not the pipe
    assert durations[len(durations) // 2] < CALL_BOUND_S, f"median call {durations[len(durations) // 2] * 1e3:.1f} ms"
    blocked = [(name, round(d * 1e3, 1)) for name, d in timed.slept if d >= BLOCKED_S]
    assert len(blocked) <= host_stalls, f"fast-side call(s) slept that long (ms): {blocked}"


class Timed:
    """Wraps the fast end's calls; keeps their durations and the calls that slept (voluntary
    context switches of this thread during the call)."""

    def __init__(self, fast: FastEnd) -> None:
        self.fast = fast
        self.durations: list[float] = []
        self.slept: list[tuple[str, float]] = []

    def __getattr__(self, name: str):
        method = getattr(self.fast, name)

        def call(*args):
            n0 = resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw
            t0 = time.perf_counter()
            try:
                return method(*args)
            finally:
                d = time.perf_counter() - t0
                self.durations.append(d)
                if resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw != n0:
                    self.slept.append((name, d))

        return call


def poll_until(condition, timeout: float, every: float = 0.0005) -> bool:
    """Call ``condition`` about every ``every`` s (a fast loop's tick) until true or ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        if condition():
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(every)


def raw_header(type_id: int, seq: int = 0) -> bytes:
    return HEADER.pack(MAGIC, VERSION, type_id, seq, 0)


@pytest.fixture
def pair():
    fast, nrt = pipe_pair(32)
    yield fast, nrt
    fast.close()
    nrt.close()


@pytest.fixture
def short_gil_slices():
    """In thread mode the fast side also waits for the GIL after each syscall, up to the switch
    interval (5 ms) when the NRT thread is busy: the thread mode's cost, which benchmarks/pipe.py
    measures, not the pipe blocking. Shorter slices keep it well inside the 5 ms sanity bound."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    yield
    sys.setswitchinterval(before)


@pytest.fixture
def peers():
    started: list[NrtPeer] = []
    yield started
    for peer in started:
        if peer.alive() and peer.mode == "subprocess":
            peer.kill()
        peer.stop(timeout=2.0)


# ---------------------------------------------------------------- messages

_VALUES = {
    "b": st.integers(-(2**7), 2**7 - 1), "B": st.integers(0, 2**8 - 1),
    "h": st.integers(-(2**15), 2**15 - 1), "H": st.integers(0, 2**16 - 1),
    "i": st.integers(-(2**31), 2**31 - 1), "I": st.integers(0, 2**32 - 1),
    "l": st.integers(-(2**31), 2**31 - 1), "L": st.integers(0, 2**32 - 1),
    "q": st.integers(-(2**63), 2**63 - 1), "Q": st.integers(0, 2**64 - 1),
    "e": st.floats(width=16), "f": st.floats(width=32), "d": st.floats(), "?": st.booleans(),
}


def messages(cls: type[Message]):
    fields = st.fixed_dictionaries({name: _VALUES[code] for name, code in cls.FIELDS})
    return st.builds(lambda f, seq, stamp: _with_header(cls(**f), seq, stamp),
                     fields, st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1))


def _with_header(msg: Message, seq: int, stamp: int) -> Message:
    msg.seq, msg.stamp_ns = seq, stamp
    return msg


def _same(a, b) -> bool:
    return (isinstance(a, float) and math.isnan(a) and math.isnan(b)) or (a == b and type(a) is type(b))


@settings(max_examples=300, deadline=None)
@given(st.one_of(messages(Grip), messages(Mixed), messages(Beat)))
def test_encode_decode_round_trip(msg):
    data = msg.encode()
    assert len(data) == HEADER.size + sum(struct.calcsize("<" + c) for _, c in msg.FIELDS)
    out = Message.decode(data)
    assert type(out) is type(msg)
    assert (out.seq, out.stamp_ns) == (msg.seq, msg.stamp_ns)
    for name, _ in msg.FIELDS:
        assert _same(getattr(out, name), getattr(msg, name)), name
    assert Message.decode(memoryview(data)).encode() == data


@settings(max_examples=500, deadline=None)
@given(st.one_of(
    st.binary(max_size=MAX_MESSAGE + 40),
    st.builds(lambda t, body: raw_header(t) + body, st.sampled_from([201, 202, 203, 0, 255]), st.binary(max_size=80)),
))
def test_decode_of_any_bytes_is_a_message_or_malformed(data):
    try:
        msg = Message.decode(data)
    except MalformedMessage:
        return
    assert isinstance(msg, Message)
    canonical = msg.encode()  # the same bytes, but for a bool byte other than 0 or 1 (read as True)
    assert len(canonical) == len(data) and canonical[:16] == data[:16]
    assert Message.decode(canonical).encode() == canonical


def test_decode_says_what_is_wrong():
    good = Grip(grasp=1.0).encode()
    for data, why in [
        (good[:10], "shorter than"), (b"XY" + good[2:], "magic"), (good[:2] + bytes([9]) + good[3:], "version"),
        (raw_header(250), "unknown message type 250"), (good + b"\0", "expected"), (good[:-1], "expected"),
    ]:
        with pytest.raises(MalformedMessage, match=why):
            Message.decode(data)


def test_fields_default_to_zero_and_unknown_fields_are_refused():
    g = Grip(grasp=0.25)
    assert (g.grasp, g.speed, g.object, g.fault, g.seq, g.stamp_ns) == (0.25, 0.0, False, 0, 0, 0)
    assert g == Grip(grasp=0.25) and g != Grip(grasp=0.5)
    with pytest.raises(TypeError, match="no field"):
        Grip(gasp=1.0)
    for bad in (Grip(fault=-1), Grip(fault=70000), Grip(grasp="open"), Mixed(v10=1e9)):
        with pytest.raises(MalformedMessage, match="cannot encode"):
            bad.encode()


def test_bad_message_definitions_are_refused(monkeypatch):
    monkeypatch.setattr(codec, "_REGISTRY", dict(codec._REGISTRY))  # whatever registers here is undone
    cases = [
        ("already", lambda: type("Clash", (Message,), {"TYPE": 201, "FIELDS": (("x", "d"),)})),
        ("MAX_MESSAGE", lambda: type("Huge", (Message,), {"TYPE": 230, "FIELDS": tuple((f"x{i}", "d") for i in range(31))})),
        ("1..255", lambda: type("NoType", (Message,), {"FIELDS": (("x", "d"),)})),
        ("1..255", lambda: type("Zero", (Message,), {"TYPE": 0})),
        ("1..255", lambda: type("Big", (Message,), {"TYPE": 256})),
        ("1..255", lambda: type("Flag", (Message,), {"TYPE": True})),
        ("struct code", lambda: type("Str", (Message,), {"TYPE": 231, "FIELDS": (("name", "8s"),)})),
        ("not allowed", lambda: type("Seq", (Message,), {"TYPE": 232, "FIELDS": (("seq", "I"),)})),
        ("duplicate", lambda: type("Twice", (Message,), {"TYPE": 233, "FIELDS": (("x", "d"), ("x", "f"))})),
        ("pairs", lambda: type("Flat", (Message,), {"TYPE": 234, "FIELDS": ("x", "d")})),
    ]
    for why, define in cases:
        with pytest.raises(MessageDefinitionError, match=why):
            define()
    assert issubclass(MessageDefinitionError, TypeError)
    assert codec._REGISTRY[201] is Grip  # a refused class registered nothing
    # 31 doubles are 264 bytes with the header; 30 (256 bytes) are the most that fit
    Fits = type("Fits", (Message,), {"TYPE": 235, "FIELDS": tuple((f"x{i}", "d") for i in range(30))})
    assert len(Fits().encode()) == MAX_MESSAGE
    # the same class defined again (a reloaded module) replaces itself
    for _ in range(2):
        class Again(Message):
            TYPE = 236
    assert codec._REGISTRY[236] is Again


# ---------------------------------------------------------------- the ends, in one process


def test_capacity_full_pipe_and_loss_counted(pair):
    fast, nrt = pair
    assert fast.capacity == nrt.capacity == 32
    results = [fast.send(Grip(grasp=i)) for i in range(3 * 32)]
    assert results == [True] * 32 + [False] * 64  # exactly capacity fit, then the fast side drops
    assert fast.counters["sent"] == 32 and fast.counters["dropped_full"] == 64
    got = [nrt.receive(timeout=0) for _ in range(32)]
    assert [m.grasp for m in got] == list(range(32)) and nrt.receive(timeout=0) is None
    assert fast.send(Grip(grasp=96))
    assert nrt.receive(timeout=1.0).seq == 96
    assert nrt.counters["lost"] == 64  # the gap in the fast side's seq: what it dropped
    # the other way the NRT side waits for room, then times out
    for _ in range(32):
        nrt.send(Beat(), timeout=0)
    t0 = time.monotonic()
    with pytest.raises(PipeTimeout):
        nrt.send(Beat(), timeout=0.05)
    assert 0.04 <= time.monotonic() - t0 < NOT_HUNG_S
    assert issubclass(PipeTimeout, TimeoutError)
    assert nrt.counters["dropped_full"] == 1
    assert len(fast.receive_all()) == 32
    assert fast.counters["lost"] == 0


def test_sequence_gaps_reordering_and_wraparound(pair):
    fast, nrt = pair
    seqs = [0, 1, 2, 5, 3, 6, 2**31, 2**32 - 1, 0, 1]  # 3, 4 lost at 5; 3 late; two big gaps; then a wrap
    with socket.fromfd(nrt.fileno(), socket.AF_UNIX, socket.SOCK_SEQPACKET) as raw:
        for seq in seqs:
            raw.send(_with_header(Grip(grasp=seq), seq, 0).encode())
        got = fast.receive_all()
    assert [m.seq for m in got] == seqs  # every valid message is delivered, in the order sent
    assert fast.counters["out_of_order"] == 1
    assert fast.counters["lost"] == 2 + (2**31 - 7) + (2**31 - 2)  # nothing lost over the wrap
    assert fast.counters["received"] == len(seqs)


def test_malformed_datagrams_are_counted_and_dropped(pair):
    fast, nrt = pair
    bad = [
        b"", b"AH", b"XY" + raw_header(201)[2:] + bytes(27), raw_header(201)[:2] + b"\x07" + raw_header(201)[3:],
        raw_header(250) + bytes(8), raw_header(201) + bytes(5), raw_header(201) + bytes(300),
    ]
    with socket.fromfd(nrt.fileno(), socket.AF_UNIX, socket.SOCK_SEQPACKET) as raw:
        raw.send(Grip(grasp=1.0).encode())
        for data in bad:
            raw.send(data)
        newest = _with_header(Grip(grasp=2.0), 1, 0)
        raw.send(newest.encode())
        raw.send(bad[0])
        t0 = time.perf_counter()
        msg = fast.receive_latest()
        assert time.perf_counter() - t0 < 2.5  # it returns: nothing here can make it wait (a host stall aside)
    assert msg == newest
    assert fast.counters["malformed"] == len(bad) + 1
    assert fast.counters["received"] == 2 and fast.counters["superseded"] == 1
    assert fast.peer_alive  # an empty datagram is not EOF
    # and the same on the NRT side, which skips them
    with socket.fromfd(fast.fileno(), socket.AF_UNIX, socket.SOCK_SEQPACKET) as raw:
        for data in bad:
            raw.send(data)
        raw.send(Grip(grasp=3.0).encode())
    assert nrt.receive(timeout=1.0) == Grip(grasp=3.0)
    assert nrt.counters["malformed"] == len(bad)


def test_eof_seen_at_once_both_ways():
    fast, nrt = pipe_pair()
    nrt.send(Grip(grasp=1.0))
    nrt.send(Grip(grasp=2.0))
    nrt.close()
    assert fast.peer_alive
    assert fast.receive_latest() == Grip(grasp=2.0)  # what was sent before the close still comes
    assert not fast.peer_alive  # and EOF is seen in the same drain
    assert fast.receive_latest() is None and fast.receive_all() == []
    assert fast.send(Grip()) is False
    fast.close()
    fast.close()  # idempotent
    with pytest.raises(PipeError, match="closed"):
        nrt.receive(timeout=0)

    fast, nrt = pipe_pair()
    fast.send(Grip(grasp=1.0))
    fast.close()
    assert nrt.receive(timeout=0) == Grip(grasp=1.0)
    with pytest.raises(PeerGone):
        nrt.receive(timeout=5.0)  # EOF at once, not after the timeout
    with pytest.raises(PeerGone):
        nrt.send(Grip(), timeout=5.0)
    assert issubclass(PeerGone, ConnectionError)
    nrt.close()


def test_what_was_sent_before_a_reset_still_comes():
    """A peer that dies with our messages unread leaves us ECONNRESET, which Linux reports
    before the messages it had sent us: they still come, then the peer is gone."""
    fast, nrt = pipe_pair()
    fast.send(Grip(grasp=9.0))  # never read by the NRT side
    nrt.send(Grip(grasp=1.0))
    nrt.send(Grip(grasp=2.0))
    nrt.close()
    assert fast.receive_latest() == Grip(grasp=2.0)
    assert not fast.peer_alive
    assert fast.receive_latest() is None and fast.send(Grip()) is False
    fast.close()

    fast, nrt = pipe_pair()
    nrt.send(Grip(grasp=9.0))  # never read by the fast side
    fast.send(Grip(grasp=1.0))
    fast.close()
    assert nrt.receive(timeout=0) == Grip(grasp=1.0)
    with pytest.raises(PeerGone):
        nrt.receive(timeout=5.0)
    nrt.close()


def test_nrt_receive_latest_waits_then_drains(pair):
    fast, nrt = pair
    t0 = time.monotonic()
    assert nrt.receive_latest(timeout=0.02) is None
    assert time.monotonic() - t0 >= 0.015
    for i in range(5):
        fast.send(Grip(grasp=i))
    assert nrt.receive_latest(timeout=1.0) == Grip(grasp=4)
    assert nrt.counters["superseded"] == 4 and nrt.counters["received"] == 5
    assert nrt.last_receive_ns > 0


@pytest.mark.asyncio
async def test_async_nrt_end(pair):
    fast, nrt = pair
    loop = asyncio.get_running_loop()
    loop.call_soon(fast.send, Grip(grasp=1.0))
    assert await asyncio.wait_for(nrt.areceive(), 2.0) == Grip(grasp=1.0)
    for _ in range(nrt.capacity):
        await nrt.asend(Beat())
    sending = asyncio.ensure_future(nrt.asend(Grip(grasp=2.0)))  # full: waits for room
    await asyncio.sleep(0.01)
    assert not sending.done()
    assert len(fast.receive_all()) == nrt.capacity
    await asyncio.wait_for(sending, 2.0)
    assert fast.receive_latest() == Grip(grasp=2.0)
    loop.call_soon(fast.close)
    with pytest.raises(PeerGone):
        await asyncio.wait_for(nrt.areceive(), 2.0)


# ---------------------------------------------------------------- peers: targets for the thread mode

_RELEASE = threading.Event()


def slow_gripper(end: NrtEnd, period: float = 0.02, **_) -> None:
    """A 50 Hz NRT loop: take the newest command, 'do blocking I/O', answer."""
    while True:
        msg = end.receive_latest(timeout=period)
        time.sleep(period)
        end.send(Grip(grasp=-1.0 if msg is None else msg.grasp), timeout=1.0)


def flood(end: NrtEnd, count: int = 0, **_) -> None:
    for i in range(count):
        end.send(Grip(grasp=float(i)))
    end.receive()  # until the fast end closes: PeerGone


def stalled(end: NrtEnd, **_) -> None:
    _RELEASE.wait(10.0)


def fails_on_first(end: NrtEnd, **_) -> None:
    end.receive()
    raise ValueError("gripper on fire")


def report_policy(end: NrtEnd, **_) -> None:
    end.send(Grip(fault=os.sched_getscheduler(0)))
    end.receive()


async def async_echo(end: NrtEnd, **_) -> None:
    while True:
        msg = await end.areceive()
        await end.asend(msg)


# ---------------------------------------------------------------- peers


def test_fast_side_with_a_slow_nrt_thread(peers, short_gil_slices):
    peer = NrtPeer.start(f"{__name__}:slow_gripper", {"period": 0.02}, mode="thread", capacity=8)
    peers.append(peer)
    assert peer.fast.capacity == 8
    fast = Timed(peer.fast)
    answers: list[Message] = []
    for _ in range(3 * peer.fast.capacity):  # a burst (a loop catching up after a stall): more than the pipe holds
        fast.send(Grip(grasp=1.0))

    def tick() -> bool:
        fast.send(Grip(grasp=1.0))
        msg = fast.receive_latest()
        if msg is not None and msg.grasp == 1.0:
            answers.append(msg)
        return len(answers) >= 5

    assert poll_until(tick, timeout=5.0, every=0.001)
    # one long call is tolerated: the drops below show that sends into the full pipe failed at
    # once (a blocking send would have waited for the NRT side instead, and dropped nothing)
    assert_never_blocked(fast, host_stalls=1)
    assert peer.fast.counters["dropped_full"] > 0  # the burst, and ~20 sends per 20 ms, into 8 places: sends fail fast
    t0 = time.monotonic()
    peer.stop(timeout=2.0)
    assert time.monotonic() - t0 < NOT_HUNG_S and not peer.alive()
    assert peer.exitcode == 0 and peer.error is None


def test_flooding_nrt_thread_newest_wins(peers, short_gil_slices):
    count = 3000
    peer = NrtPeer.start(f"{__name__}:flood", {"count": count}, mode="thread")
    peers.append(peer)
    fast = Timed(peer.fast)
    seen: list[float] = []

    def tick() -> bool:
        msg = fast.receive_latest()
        if msg is not None:
            seen.append(msg.grasp)
        return bool(seen) and seen[-1] == count - 1

    assert poll_until(tick, timeout=10.0)
    assert_never_blocked(fast)
    assert seen == sorted(set(seen))  # always newer, never the same twice
    counters = peer.fast.counters
    assert counters["received"] == count  # the NRT side waits when full: nothing lost
    assert counters["superseded"] == count - len(seen)
    assert counters["lost"] == counters["malformed"] == counters["out_of_order"] == 0
    assert peer.fast.last_receive_ns > 0
    peer.stop(timeout=2.0)
    assert peer.exitcode == 0


def test_stalled_nrt_thread_and_bounded_stop(peers, short_gil_slices):
    _RELEASE.clear()
    peer = NrtPeer.start(f"{__name__}:stalled", mode="thread")
    peers.append(peer)
    fast = Timed(peer.fast)
    sent = [fast.send(Grip(grasp=i)) for i in range(3 * peer.fast.capacity)]
    assert sent.count(True) == peer.fast.capacity
    assert all(fast.receive_latest() is None for _ in range(100))
    assert_never_blocked(fast)
    assert peer.fast.counters["dropped_full"] == 2 * peer.fast.capacity
    t0 = time.monotonic()
    peer.stop(timeout=0.1)  # the target never reads: stop gives up on the join, bounded
    assert time.monotonic() - t0 < NOT_HUNG_S  # gave up on the join instead of waiting
    assert peer.alive() and peer.exitcode is None
    with pytest.raises(PipeError, match="cannot be killed"):
        peer.kill()
    _RELEASE.set()
    peer._thread.join(5.0)
    assert not peer.alive() and peer.exitcode == 0


def test_nrt_thread_that_raises_is_seen(peers):
    peer = NrtPeer.start(f"{__name__}:fails_on_first", mode="thread")
    peers.append(peer)
    assert peer.pid is None and peer.mode == "thread"
    assert peer.fast.send(Grip())
    assert poll_until(lambda: peer.fast.receive_latest() is None and not peer.fast.peer_alive, timeout=5.0)
    assert peer.fast.send(Grip()) is False
    assert not peer.alive()
    assert peer.exitcode == 1
    assert peer.error == "ValueError: gripper on fire"


def test_async_target_in_a_thread(peers):
    peer = NrtPeer.start(f"{__name__}:async_echo", mode="thread")
    peers.append(peer)
    answers: list[Message] = []
    peer.fast.send(Grip(grasp=7.0))
    assert poll_until(lambda: answers.extend(peer.fast.receive_all()) or answers, timeout=5.0)
    assert answers == [Grip(grasp=7.0)]
    peer.stop(timeout=2.0)
    assert not peer.alive() and peer.exitcode == 0


def test_nrt_thread_drops_an_inherited_realtime_policy(peers):
    require_root("SCHED_FIFO for the thread that starts the peer")
    started: list[NrtPeer] = []

    def start_from_a_fifo_thread() -> None:  # as if the fast loop's thread started it
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        started.append(NrtPeer.start(f"{__name__}:report_policy", mode="thread"))

    starter = threading.Thread(target=start_from_a_fifo_thread)
    starter.start()
    starter.join(5.0)
    (peer,) = started
    peers.append(peer)
    answers: list[Message] = []
    assert poll_until(lambda: answers.extend(peer.fast.receive_all()) or answers, timeout=5.0)
    assert answers[0].fault == os.SCHED_OTHER


def test_peer_start_refuses_bad_arguments():
    with pytest.raises(ValueError, match="mode"):
        NrtPeer.start("benchmarks.pipe_targets:echo", mode="fork")
    with pytest.raises(TypeError):
        NrtPeer.start("benchmarks.pipe_targets:echo", {"when": object()}, mode="thread")
    with pytest.raises(ValueError, match=r"package.module:function"):
        NrtPeer.start("aiohal.pipe", mode="thread")
    with pytest.raises(AttributeError):
        NrtPeer.start("aiohal.pipe:no_such_target", mode="thread")


def test_subprocess_echo_and_clean_stop(peers):
    peer = NrtPeer.start("benchmarks.pipe_targets:echo", mode="subprocess")
    peers.append(peer)
    assert peer.pid and peer.pid != os.getpid() and peer.alive()
    fast = peer.fast
    sent = Grip(grasp=1.0)
    assert fast.send(sent) and fast.send(Beat())
    answers: list[Message] = []
    assert poll_until(lambda: answers.extend(fast.receive_all()) or len(answers) == 2, timeout=10.0)
    assert answers == [Grip(grasp=1.0), Beat()]
    assert [m.seq for m in answers] == [0, 1]
    assert answers[0].stamp_ns == sent.stamp_ns < fast.last_receive_ns  # the echo keeps the sender's stamp
    peer.stop(timeout=10.0)
    # exit code 0: it returned on the closed pipe; a SIGTERM or SIGKILL from stop() would show
    # as -15 or -9 (a fixed time bound here failed once when the host stalled the VM for 2 s)
    assert not peer.alive() and peer.exitcode == 0
    peer.stop()  # idempotent


def test_subprocess_killed_mid_run_is_detected(peers):
    peer = NrtPeer.start("benchmarks.pipe_targets:echo", mode="subprocess")
    peers.append(peer)
    fast = Timed(peer.fast)
    echoes: list[Message] = []

    def tick() -> bool:
        fast.send(Beat())
        echoes.extend(fast.receive_all())
        return len(echoes) >= 20

    assert poll_until(tick, timeout=10.0, every=0.001)
    peer.kill()
    assert poll_until(lambda: not peer.alive(), timeout=5.0)
    assert peer.exitcode == -signal.SIGKILL
    fast.receive_latest()  # the next receive sees the EOF
    assert not peer.fast.peer_alive
    assert fast.send(Beat()) is False and fast.receive_latest() is None
    assert_never_blocked(fast)
    assert peer.fast.counters["lost"] == 0 and peer.fast.counters["malformed"] == 0


def test_stopped_subprocess_never_blocks_the_fast_side_and_stop_escalates(peers):
    peer = NrtPeer.start("benchmarks.pipe_targets:echo", mode="subprocess")
    peers.append(peer)
    os.kill(peer.pid, signal.SIGSTOP)  # the NRT side stalls completely (it cannot even be scheduled)
    fast = Timed(peer.fast)
    sent = [fast.send(Grip(grasp=i)) for i in range(3 * peer.fast.capacity)]
    assert sent.count(True) == peer.fast.capacity and sent[-1] is False
    assert all(fast.receive_latest() is None for _ in range(100))
    assert_never_blocked(fast)
    assert peer.fast.peer_alive  # stalled is not dead
    t0 = time.monotonic()
    peer.stop(timeout=0.3)  # EOF is not read, SIGTERM stays pending on a stopped process: SIGKILL ends it
    assert time.monotonic() - t0 < NOT_HUNG_S
    assert peer.exitcode == -signal.SIGKILL


def test_subprocess_target_that_fails_exits_1_with_one_line(peers, capfd):
    peer = NrtPeer.start("aiohal.pipe:no_such_target", mode="subprocess")
    peers.append(peer)
    assert poll_until(lambda: not peer.alive(), timeout=10.0, every=0.005)
    assert peer.exitcode == 1 and peer.error is None
    peer.fast.receive_latest()
    assert not peer.fast.peer_alive
    lines = [line for line in capfd.readouterr().err.splitlines() if "aiohal.pipe" in line]
    assert len(lines) == 1 and "no_such_target" in lines[0] and "AttributeError" in lines[0]
