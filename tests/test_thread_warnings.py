"""Warnings captured per thread (warptex.thread_warnings)."""

import sys
import threading
import types
import warnings

import pytest

from warptex.thread_warnings import Warned, captured, library_warnings, warn


def _library(name: str):
    """A function that warns as code of the imported module ``name`` does."""
    module = sys.modules.setdefault(name, types.ModuleType(name))
    exec("import warnings\ndef say(words):\n    warnings.warn(words)\n", module.__dict__)
    return module.say


def test_a_capture_takes_this_thread_s_warnings_and_no_other_thread_s():
    with pytest.warns(UserWarning, match="from elsewhere") as shown, captured() as said:
        warn("here", RuntimeWarning)
        other = threading.Thread(target=warn, args=("from elsewhere",))
        other.start()
        other.join()
    assert said == [Warned("here", RuntimeWarning)]
    assert [str(w.message) for w in shown] == ["from elsewhere"]


def test_captures_that_overlap_on_two_threads_each_keep_their_own():
    """The order that lost warnings with catch_warnings: the second capture opened after
    the first and closed before it, while the first one's thread warned."""
    steps = [threading.Event() for _ in range(3)]
    got = {}

    def second():
        steps[0].wait()
        with captured() as said:
            steps[1].set()
            steps[2].wait()
            warn("second")
        got["second"] = said

    thread = threading.Thread(target=second)
    thread.start()
    with captured() as said:
        steps[0].set()
        steps[1].wait()
        warn("first, while the other is open")
        steps[2].set()
        thread.join()
        warn("first, after it closed")
    assert [w.message for w in said] == ["first, while the other is open",
                                         "first, after it closed"]
    assert got["second"] == [Warned("second", UserWarning)]
    with pytest.warns(UserWarning, match="none open"):  # no capture left behind
        warn("none open")


def test_captures_nest_and_the_innermost_takes_them():
    with captured() as outer:
        warn("outer")
        with captured() as inner:
            warn("inner")
        warn("outer again")
    assert [w.message for w in outer] == ["outer", "outer again"]
    assert [w.message for w in inner] == ["inner"]


def test_warn_points_where_warnings_warn_would():
    def caller():
        warn("said", stacklevel=2)

    with pytest.warns(UserWarning, match="said") as shown:
        caller()
    assert shown[0].filename == __file__


def test_a_library_s_warnings_are_each_taken_on_this_thread_and_others_passed_on():
    say = _library("somelib.exif")
    outside = _library("elsewhere")
    with pytest.warns(UserWarning) as shown, warnings.catch_warnings():
        warnings.simplefilter("default")  # Python's: the same words are said once
        say("corrupt data")
        with library_warnings("somelib") as said:
            say("corrupt data")  # of another file: no repeat
            say("corrupt data")
            other = threading.Thread(target=outside, args=("another thread's",))
            other.start()
            other.join()
        say("after")
    assert said == [Warned("corrupt data", UserWarning)] * 2
    assert [str(w.message) for w in shown] == ["corrupt data", "another thread's", "after"]


def test_a_library_capture_leaves_the_process_s_hook_and_filters_as_it_found_them():
    hook, filters = warnings.showwarning, list(warnings.filters)
    with library_warnings("somelib"):
        assert warnings.showwarning is not hook
    assert warnings.showwarning is hook
    assert warnings.filters == filters


def test_library_captures_nest_and_the_inner_one_leaves_the_outer_one_whole():
    say = _library("somelib")
    with pytest.warns(UserWarning) as shown, warnings.catch_warnings():
        warnings.simplefilter("default")
        with library_warnings("somelib") as outer:
            with library_warnings("somelib") as inner:
                say("corrupt data")
            say("corrupt data")
            say("corrupt data")
        say("after")
    assert inner == [Warned("corrupt data", UserWarning)]
    assert outer == [Warned("corrupt data", UserWarning)] * 2
    assert [str(w.message) for w in shown] == ["after"]


def test_library_captures_that_overlap_on_two_threads_each_keep_their_own():
    say = _library("somelib")
    steps = [threading.Event() for _ in range(3)]
    got = {}

    def second():
        with library_warnings("somelib") as said:
            steps[0].set()
            steps[1].wait()  # the first one closed
            say("second")
        got["second"] = said
        steps[2].set()

    hook = warnings.showwarning
    thread = threading.Thread(target=second, daemon=True)  # not waited for where it hangs
    with library_warnings("somelib") as said:
        thread.start()
        assert steps[0].wait(60), "the second capture did not open while the first was"
        say("first")
    steps[1].set()
    assert steps[2].wait(60), "the second capture did not close"
    thread.join()
    assert said == [Warned("first", UserWarning)]
    assert got["second"] == [Warned("second", UserWarning)]
    assert warnings.showwarning is hook


def test_another_s_capture_that_closes_last_leaves_no_dead_capture_behind():
    """Warp's logger, say, on another thread: its capture opens while a library capture
    is open, and puts back the hook it found after that one closed."""
    say = _library("somelib")
    with pytest.warns(UserWarning, match="later") as shown:
        ours = library_warnings("somelib")
        ours.__enter__()
        theirs = warnings.catch_warnings()
        theirs.__enter__()
        ours.__exit__(None, None, None)
        theirs.__exit__(None, None, None)
        say("later")
    assert [str(w.message) for w in shown] == ["later"]


def test_a_library_capture_leaves_other_modules_words_said_once_said():
    """The plugin says an exemplar's warning once for two textures of one file: a library
    capture opened in between must not make it forget it said so."""
    plugin = _library("someplugin")
    with pytest.warns(UserWarning) as shown, warnings.catch_warnings():
        warnings.simplefilter("default")
        plugin("alpha dropped")
        with library_warnings("somelib"):
            pass
        plugin("alpha dropped")
    assert [str(w.message) for w in shown] == ["alpha dropped"]
