"""Warnings captured per thread (warptex.thread_warnings)."""

import os
import sys
import threading
import types
import warnings

import pytest

from warptex.thread_warnings import Warned, captured, library_warnings, warn


def _library(name: str):
    """A function that warns as code of the imported module ``name``, a package's file
    (beside its ``__init__.py``) or a top-level module's, does."""
    top = name.partition(".")[0]
    folder = os.path.join(os.path.abspath("nowhere"), top)
    for each in dict.fromkeys((top, name)):
        module = sys.modules.setdefault(each, types.ModuleType(each))
        module.__file__ = os.path.join(folder, "__init__.py" if each == top else
                                       f"{each.rpartition('.')[2]}.py")
    code = compile("import warnings\ndef say(words):\n    warnings.warn(words)\n",
                   module.__file__, "exec")
    exec(code, module.__dict__)
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
        line = sys._getframe().f_lineno + 1
        caller()
    assert (shown[0].filename, shown[0].lineno) == (__file__, line)


def test_a_capture_left_by_an_error_takes_no_more_warnings():
    with pytest.raises(ValueError), captured():
        raise ValueError
    with pytest.warns(UserWarning, match="after"):
        warn("after")


def test_a_library_s_warnings_are_taken_on_this_thread_and_others_passed_on():
    say = _library("somelib.exif")
    outside = _library("elsewhere")
    with pytest.warns(UserWarning) as shown, warnings.catch_warnings():
        warnings.simplefilter("default")  # Python's: the same words are said once
        say("corrupt data")
        with library_warnings("somelib") as said:
            say("corrupt data")  # of this file: no repeat
            say("corrupt data")
            outside("this thread's, not the library's")
            other = threading.Thread(target=say, args=("another thread's",))
            other.start()
            other.join()
        with library_warnings("somelib") as said_of_another_file:
            say("corrupt data")
        say("after")
    assert said == said_of_another_file == [Warned("corrupt data", UserWarning)]
    assert [str(w.message) for w in shown] == [
        "corrupt data", "this thread's, not the library's", "another thread's", "after"]


def test_a_library_s_warnings_keep_the_process_s_filters():
    say = _library("somelib")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with library_warnings("somelib") as said:
            say("corrupt data")
        assert said == []
        warnings.simplefilter("error")
        with pytest.raises(UserWarning, match="corrupt data"), library_warnings("somelib"):
            say("corrupt data")


def test_a_library_capture_leaves_the_process_s_hook_and_filters_as_it_found_them():
    hook, filters = warnings.showwarning, list(warnings.filters)
    with library_warnings("somelib"):
        assert warnings.showwarning is not hook
    assert warnings.showwarning is hook
    assert warnings.filters == filters


def test_library_captures_nest_and_the_innermost_takes_them():
    say = _library("somelib")
    with library_warnings("somelib") as outer:
        with library_warnings("somelib") as inner:
            say("inner")
        say("outer")
    assert inner == [Warned("inner", UserWarning)]
    assert outer == [Warned("outer", UserWarning)]


def test_library_captures_on_two_threads_take_turns_and_each_keeps_its_own():
    """The library's record of words said is one for all threads: the same words said in a
    capture open on another thread meanwhile would not be said again."""
    say = _library("somelib")
    first_open, second_tried = threading.Event(), threading.Event()
    got = {}

    def second():
        first_open.wait()
        second_tried.set()
        with library_warnings("somelib") as said:
            say("corrupt data")
        got["second"] = said

    hook = warnings.showwarning
    thread = threading.Thread(target=second, daemon=True)  # not waited for where it hangs
    thread.start()
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("default")  # Python's: the same words are said once
        with library_warnings("somelib") as said:
            first_open.set()
            assert second_tried.wait(60)
            say("corrupt data")
            assert "second" not in got  # it waits for its turn
        thread.join(60)
    assert said == got["second"] == [Warned("corrupt data", UserWarning)]
    assert shown == []
    assert warnings.showwarning is hook


def _show_elsewhere(message, category, filename, lineno, file=None, line=None):
    """Another's hook, for a while."""


def test_another_s_capture_that_overlaps_library_captures_leaves_the_hook_found():
    """Warp's logger, say, on another thread: its capture puts its own hook in for a while,
    meanwhile library captures open and close, and it puts back the hook it found."""
    say = _library("somelib")
    with pytest.warns(UserWarning, match="later") as shown:
        hook = warnings.showwarning
        first = library_warnings("somelib")
        first.__enter__()
        theirs = warnings.catch_warnings()
        theirs.__enter__()
        warnings.showwarning = _show_elsewhere
        second = library_warnings("somelib")
        second.__enter__()
        first.__exit__(None, None, None)
        theirs.__exit__(None, None, None)  # puts back the dispatcher
        second.__exit__(None, None, None)
        assert warnings.showwarning is hook
        theirs = warnings.catch_warnings()  # and once more, closing after the captures
        theirs.__enter__()
        with library_warnings("somelib"):
            pass
        theirs.__exit__(None, None, None)
        say("later")
    assert [str(w.message) for w in shown] == ["later"]


def test_a_hook_that_passes_warnings_back_to_the_dispatcher_does_not_loop():
    """logging.captureWarnings put in while a library capture is open passes warnings
    with a file on to the dispatcher, and the next capture finds it."""
    import io
    import logging

    shown = io.StringIO()
    with warnings.catch_warnings():
        with library_warnings("somelib"):
            logging.captureWarnings(True)
        try:
            with library_warnings("somelib"):
                warnings.showwarning("words", UserWarning, "where.py", 3, shown)
        finally:
            logging.captureWarnings(False)
    assert "where.py:3: UserWarning: words" in shown.getvalue()


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


def test_every_warning_passed_on_in_a_library_capture_reaches_the_hook_found():
    outside = _library("elsewhere")
    with pytest.warns(UserWarning) as shown, library_warnings("somelib"):
        outside("one")
        outside("two")
    assert [str(w.message) for w in shown] == ["one", "two"]


def test_a_capture_of_a_module_loaded_from_no_file_passes_warnings_on(monkeypatch):
    monkeypatch.setitem(sys.modules, "fileless", types.ModuleType("fileless"))
    with pytest.warns(UserWarning, match="elsewhere"), library_warnings("fileless"):
        warnings.warn("elsewhere", stacklevel=1)


def test_a_package_of_a_longer_name_is_not_the_library():
    """``somelib2`` is not ``somelib``: its warnings are passed on, and what it said before
    stays said."""
    say = _library("somelib")
    other = _library("somelib2")
    with pytest.warns(UserWarning) as shown, warnings.catch_warnings():
        warnings.simplefilter("default")
        other("words")
        with library_warnings("somelib") as said:
            other("words")
            other("new words")
            say("mine")
    assert said == [Warned("mine", UserWarning)]
    assert [str(w.message) for w in shown] == ["words", "new words"]
