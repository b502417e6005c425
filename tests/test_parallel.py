"""Splitting one Warp launch over CPU threads gives the result of one launch."""

import multiprocessing
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import warp as wp

from warptex.parallel import MIN_SPLIT, in_child_process, launch_ranges

REPO = Path(__file__).resolve().parent.parent


@wp.kernel
def _double(first: int, a: wp.array(dtype=Any), out: wp.array(dtype=wp.float32)):
    i = first + wp.tid() // 2
    if wp.tid() % 2 == 0:
        out[i] = wp.float32(a[i]) * 2.0


def test_split_generic_launch_equals_one_launch(warp_device):
    n = 4 * MIN_SPLIT + 3
    values = np.arange(n) % 251
    for dtype in (wp.uint16, wp.int32):  # each dtype is a new overload, built on first use
        a = wp.array(values, dtype=dtype, device="cpu")
        out = wp.full(n, -1.0, dtype=wp.float32, device="cpu")
        launch_ranges(_double, 5, n, [a], [out], per_item=2)
        expected = np.where(np.arange(n) >= 5, 2.0 * values, -1.0)
        assert np.array_equal(out.numpy(), expected.astype(np.float32))


@wp.kernel
def _busy(first: int, out: wp.array(dtype=wp.float32)):
    i = first + wp.tid()
    x = wp.float32(0.0)
    for k in range(2000):
        x = x + wp.sin(float(i + k))
    out[i] = x


def test_a_stopped_split_launch_ends_its_ranges_before_going_on(monkeypatch, warp_device):
    """Ctrl-C while the calling thread waits for the other ranges: the KeyboardInterrupt goes
    on only once no range runs, as the caller may then free the arrays they use."""
    import concurrent.futures

    import warptex.parallel as parallel

    monkeypatch.setattr(parallel, "THREADS", 2)
    jobs = []
    pool = parallel._pool()
    submit = pool.submit

    def recorded(*args, **kwargs):
        jobs.append(submit(*args, **kwargs))
        return jobs[-1]

    result = concurrent.futures.Future.result

    def stopped(self, timeout=None):
        concurrent.futures.Future.result = result
        for _ in range(10**6):  # the stop comes once a range runs
            if any(job.running() for job in jobs):
                break
        raise KeyboardInterrupt

    out = wp.zeros(64 * MIN_SPLIT, dtype=wp.float32, device="cpu")
    launch_ranges(_busy, 0, MIN_SPLIT, [], [out])  # builds the module first
    monkeypatch.setattr(pool, "submit", recorded)
    monkeypatch.setattr(concurrent.futures.Future, "result", stopped)
    launch = parallel.launch
    # Ranges that take a while: one still running when the stop comes is waited for.
    monkeypatch.setattr(parallel, "launch", lambda *a, **k: (time.sleep(0.3), launch(*a, **k)))
    with pytest.raises(KeyboardInterrupt):
        launch_ranges(_busy, 0, out.shape[0], [], [out])
    assert jobs and all(job.done() for job in jobs)


_BUILD_ONCE = """
import numpy as np
import warp as wp

import warptex.parallel as parallel

parallel.THREADS = 2  # split even on a one-core machine


@wp.kernel
def fill(first: int, out: wp.array(dtype=wp.float32)):
    i = first + wp.tid()
    out[i] = float(i)


out = wp.zeros(2 * parallel.MIN_SPLIT, dtype=wp.float32, device="cpu")
parallel.launch_ranges(fill, 0, out.shape[0], [], [out])
assert np.array_equal(out.numpy(), np.arange(out.shape[0], dtype=np.float32))
"""


def test_split_launch_builds_its_module_once(tmp_path):
    """A split launch builds the variant of the module that CPU launches use, and no other:
    a second variant costs a whole compile on a cold kernel cache."""
    script = tmp_path / "build_once.py"
    script.write_text(_BUILD_ONCE)
    cache = tmp_path / "kernels"
    env = {**os.environ, "WARP_CACHE_PATH": str(cache)}
    subprocess.run([sys.executable, str(script)], check=True, env=env, cwd=REPO,
                   capture_output=True)
    built = [p.name for p in cache.rglob("*") if p.is_dir() and "__main__" in p.name]
    assert len(built) == 1, built


def test_threads_follow_the_cores_the_process_may_use(monkeypatch):
    """A container or ``taskset`` may allow fewer cores than the machine has: threads
    beyond them would only take turns."""
    from warptex import machine, parallel

    assert min(machine.usable_cores(), 8) == parallel.THREADS
    if not hasattr(os, "sched_getaffinity"):
        assert machine.usable_cores() == (os.cpu_count() or 1)
        return
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3, 5})
    monkeypatch.setattr(machine, "_PROC_CGROUP", Path("/nonexistent"))  # no CPU quota
    assert machine.usable_cores() == 3


@wp.kernel
def _count_every_thread(first: int, per_item: int, hits: wp.array(dtype=wp.int32)):
    wp.atomic_add(hits, first * per_item + wp.tid(), 1)


@pytest.mark.parametrize("per_item", [1, 3])
def test_split_launch_runs_every_thread_of_every_item_once(per_item, monkeypatch, warp_device):
    """Counts, not idempotent writes: an item launched twice or a thread left out shows.
    Item counts around MIN_SPLIT, starts off zero, 2 and 3 threads."""
    from warptex import parallel

    for threads in (2, 3):
        monkeypatch.setattr(parallel, "THREADS", threads)
        for start, n in [(0, parallel.MIN_SPLIT), (7, parallel.MIN_SPLIT - 1),
                         (5, parallel.MIN_SPLIT + 1), (1, 2 * parallel.MIN_SPLIT + 5)]:
            hits = wp.zeros((start + n) * per_item, dtype=wp.int32, device="cpu")
            # the kernel's thread t of a launch from ``first`` is thread first*per_item + t
            # of the whole; items start..stop are threads start*per_item..stop*per_item
            parallel.launch_ranges(_count_every_thread, start, start + n, [per_item], [hits],
                                   per_item=per_item)
            got = hits.numpy()
            assert np.all(got[: start * per_item] == 0)
            assert np.all(got[start * per_item:] == 1), (threads, start, n)


class _Stopped(Exception):
    pass


def test_a_nearest_neighbour_query_stopped_by_a_signal_ends_before_the_signal_goes_on(
        monkeypatch):
    """SciPy's threaded queries read the tree until they end: Ctrl-C or SIGTERM during one
    reaches its handler once the query has ended (the tree freed under a running query
    ended the process with a segmentation fault), and the handlers are as before."""
    import signal
    import threading
    import time

    from scipy.spatial import cKDTree

    from warptex.parallel import nearest

    points = np.random.default_rng(0).random((500, 3))
    tree = cKDTree(points)
    ended = threading.Event()

    def stop(signum, frame):
        raise _Stopped(signum)

    class Stopped:
        def __init__(self, signum):
            self.signum = signum

        def query(self, queries, **options):
            os.kill(os.getpid(), self.signum)
            time.sleep(0.3)
            ended.set()
            return tree.query(queries, **options)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        for signum, raised in ((signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, _Stopped)):
            ended.clear()
            with pytest.raises(raised):
                nearest(Stopped(signum), points[:5], k=2)
            assert ended.is_set()
        assert signal.getsignal(signal.SIGTERM) is stop
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)
    np.testing.assert_array_equal(nearest(tree, points[:5], k=2)[1],
                                  tree.query(points[:5], k=2)[1])


def test_a_long_query_runs_in_parts_and_a_stop_waits_for_one(monkeypatch):
    """A query held Ctrl-C and SIGTERM back to its end (100 s for one axis of `compare
    --size 128`'s completeness): it runs in parts, a stop ends it after the part under way,
    and the parts give what one query would."""
    from scipy.spatial import cKDTree

    import warptex.parallel

    points = np.random.default_rng(1).random((1000, 4))
    tree = cKDTree(points)
    monkeypatch.setattr(warptex.parallel, "_FIRST_QUERY_ROWS", 7)
    asked = []

    class Counted:
        def query(self, queries, **options):
            asked.append(len(queries))
            return tree.query(queries, **options)

    found = warptex.parallel.nearest(Counted(), points[::-1], k=3)
    assert len(asked) > 1 and sum(asked) == len(points)
    # However fast a part seems, the next is at most 4 times as large: one part sized from
    # a timer's tick would take the rest of a long query, and hold a stop back with it.
    ticks = iter(range(10**6))
    monkeypatch.setattr(warptex.parallel.time, "perf_counter", lambda: next(ticks) * 1e-9)
    asked.clear()
    warptex.parallel.nearest(Counted(), points, k=1)
    assert asked[:3] == [7, 28, 112]
    monkeypatch.undo()
    monkeypatch.setattr(warptex.parallel, "_FIRST_QUERY_ROWS", 7)
    expected = tree.query(points[::-1], k=3)
    for mine, theirs in zip(found, expected, strict=True):
        np.testing.assert_array_equal(mine, theirs)
    asked.clear()

    class Stopped:
        def query(self, queries, **options):
            asked.append(len(queries))
            os.kill(os.getpid(), signal.SIGINT)
            return tree.query(queries, **options)

    with pytest.raises(KeyboardInterrupt):
        warptex.parallel.nearest(Stopped(), points, k=1)
    assert asked == [7]


def test_every_signal_held_back_during_a_query_reaches_its_handler():
    """Ctrl-C and SIGTERM both during one query: each goes on to its own handler after it
    (SIGTERM was lost behind Ctrl-C's KeyboardInterrupt), and the handlers are as before."""
    import signal

    from scipy.spatial import cKDTree

    from warptex.parallel import nearest

    points = np.random.default_rng(0).random((100, 3))
    tree = cKDTree(points)
    reached = []

    def record(signum, frame):
        reached.append(signum)

    class Stopped:
        def query(self, queries, **options):
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)
            assert reached == []  # held back while the query runs
            return tree.query(queries, **options)

    previous = {n: signal.signal(n, record) for n in (signal.SIGINT, signal.SIGTERM)}
    try:
        nearest(Stopped(), points[:3], k=1)
        for _ in range(1000):  # Python runs handlers between bytecodes
            if len(reached) == 2:
                break
        assert sorted(reached) == sorted([signal.SIGINT, signal.SIGTERM])
        assert all(signal.getsignal(n) is record for n in previous)
    finally:
        for n, handler in previous.items():
            signal.signal(n, handler)


@pytest.mark.parametrize("error", [KeyboardInterrupt, ValueError])
@pytest.mark.parametrize("when", ["holding", "giving back"])
def test_a_stop_between_two_handler_swaps_leaves_every_handler_as_it_was(monkeypatch, when,
                                                                         error):
    """Blocking holds a signal from the calling thread only: one sent to the process comes
    through another thread, and signal.signal runs its handler first. Raised between the
    two swaps, it left Ctrl-C's handler swapped for good (later SIGTERMs then went unseen);
    a caller's handler may raise anything, a ValueError too, which is no refusal of
    signal.signal's."""
    from warptex import parallel

    def terminated(signum, frame):
        raise KeyboardInterrupt

    previous = {n: signal.signal(n, terminated) for n in (signal.SIGINT, signal.SIGTERM)}
    real = signal.signal
    calls = []

    def signal_meanwhile(number, handler):
        calls.append(number)
        # The second swap of the block's start, or of its end, finds a stop that came.
        if len(calls) == (2 if when == "holding" else 4):
            raise error
        return real(number, handler)

    monkeypatch.setattr(parallel.signal, "signal", signal_meanwhile)
    try:
        with pytest.raises(error), parallel.deferred_stops():
            pass
        monkeypatch.undo()
        assert all(signal.getsignal(n) is terminated for n in previous)
    finally:
        monkeypatch.undo()
        for n, handler in previous.items():
            signal.signal(n, handler)


def test_blocked_holds_the_signals_and_gives_the_mask_back():
    """Handlers are swapped and held-back stops raised again with the signals blocked: one
    delivered at once there, whose handler raised, left the next unraised."""
    from warptex.stops import blocked

    if not hasattr(signal, "pthread_sigmask"):
        pytest.skip("no signal masks (Windows)")
    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    with blocked((signal.SIGINT, signal.SIGTERM)):
        held = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    assert {signal.SIGINT, signal.SIGTERM} <= held
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before


def test_deferred_stops_on_another_thread_run_the_block_as_it_is(errors_on_a_thread):
    """Only the main thread may set handlers (ValueError elsewhere), and only it is
    interrupted: a worker thread's query runs as it would without them."""
    from warptex.stops import deferred_stops

    ran = []

    def work() -> None:
        with deferred_stops():
            ran.append(True)

    assert (errors_on_a_thread(work), ran) == ([], [True])


_UNSEEN_HANDLER = """
import signal
from warptex.stops import deferred_stops
real = signal.getsignal
handler = real(signal.SIGTERM)
signal.getsignal = lambda number: None if number == signal.SIGTERM else real(number)
with deferred_stops():
    assert real(signal.SIGTERM) is handler
assert real(signal.SIGTERM) is handler
print("kept")
"""


def test_a_handler_python_cannot_see_is_left_in_place():
    """A handler installed from C reads as None and cannot be set back from Python: it is
    left as it is. Setting None again raised a TypeError after the block, which the swap
    once retried for ever: hence a process of its own, with a time limit."""
    done = subprocess.run([sys.executable, "-c", _UNSEEN_HANDLER], capture_output=True,
                          text=True, timeout=60)
    assert done.stdout.strip() == "kept", done.stderr


def _backtracking() -> None:
    """Minutes in one C call that holds the GIL, as xatlas' unwrapping does."""
    re.fullmatch(r"(a+)+b", "a" * 64)


def test_a_stop_reaches_a_long_c_call_run_in_a_child_process():
    """Ctrl-C or SIGTERM waited for xatlas' unwrapping to end (18 s on the bunny): run in a
    child process, the call is stopped with it and the stop goes on at once."""
    assert in_child_process(pow, 2, 10) == 1024
    threading.Timer(1.0, signal.pthread_kill, (threading.get_ident(), signal.SIGINT)).start()
    with pytest.raises(KeyboardInterrupt):
        in_child_process(_backtracking)
    assert multiprocessing.active_children() == []


def _timed_out() -> None:
    raise TimeoutError("the function's own")


def test_a_timeout_the_child_raises_reaches_the_caller():
    """The function's TimeoutError passed for the wait's: with ``while_waiting`` that was
    called forever, without it the error was a TypeError."""
    waited = []

    def while_waiting():
        waited.append(1)
        if len(waited) > 100:  # the child ended at once: this is the endless loop
            raise AssertionError("while_waiting called on and on")

    for each in (None, while_waiting):
        with pytest.raises(TimeoutError, match="the function's own"):
            in_child_process(_timed_out, while_waiting=each)


_FORKED = """
import multiprocessing, sys
import numpy as np
import warptex.parallel as parallel
parallel.THREADS = 2  # a pool of threads, on a machine of one core too
from warptex.candidates import precompute
from warptex.synthesis import Synthesizer
syn = Synthesizer(precompute(sys.argv[1]), seed=1, device="cpu")
parent = syn.box((0, 0, 0), (16, 16, 16))  # split launches: the pool's threads start

def child(_):
    return Synthesizer(syn.candidates, seed=1, device="cpu").box((0, 0, 0), (16, 16, 16))

with multiprocessing.get_context("fork").Pool(1) as pool:
    forked = pool.apply_async(child, (0,)).get(timeout=240)
print(np.array_equal(parent, forked))
"""


def test_a_forked_process_launches_on_threads_of_its_own(data_dir):
    """A child forked after a split launch (multiprocessing's default on Linux) inherited
    the pool without its threads, and its first split launch waited for ever; it makes its
    own, with the same voxels."""
    run = subprocess.run([sys.executable, "-c", _FORKED, str(data_dir / "granite_64.png")],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and run.stdout.split() == ["True"], run.stderr[-2000:]


_STOPPED_AS_A_THREAD_STARTS = """
import os, signal, threading

from warptex import parallel

parallel.THREADS = 2  # a pool of more than one thread, whatever the machine
started = threading.Thread.start


def start_then_stop(thread):
    started(thread)
    if thread.name.startswith("warptex") and threading.Thread.start is start_then_stop:
        threading.Thread.start = started
        os.kill(os.getpid(), signal.SIGINT)  # as Ctrl-C comes with the thread just running
        for _ in range(1000):  # the handler runs at the loop's next turn
            pass


threading.Thread.start = start_then_stop
try:
    parallel._pool().submit(print, "ran").result()  # the first launch's submission
except KeyboardInterrupt:
    print("interrupted")
"""


def test_a_stop_as_the_pool_starts_a_thread_lets_the_process_end():
    """Ctrl-C inside Thread.start, the thread already running: the pool had not recorded
    it, and the interpreter's exit waited for it for ever (only kill -9 ended a command so
    stopped, Ctrl-C and SIGTERM being ignored by then)."""
    run = subprocess.run([sys.executable, "-c", _STOPPED_AS_A_THREAD_STARTS],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and run.stdout.split() == ["interrupted"], run.stderr[-2000:]
