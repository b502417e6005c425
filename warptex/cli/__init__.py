"""The ``warptex`` command line: :func:`main` runs a command.

The package reads like the commands: ``exemplars`` (info, precompute), ``cache``, ``volumes``
(volume, slice), ``meshes`` (bake, cut), ``compare`` and ``render`` each declare their
commands' arguments (``add_NAME_parser``) and run them (``run_NAME``); ``options`` holds the
options several commands share and what they load, ``common`` the refusals before any work and
the writing of outputs, ``parsing`` the parser and its help, ``console`` progress bars in logs
and stops by Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from collections.abc import Sequence

from warptex.cli.common import WRITTEN, CliError
from warptex.cli.console import (
    SIGTERM_RECEIVED,
    SigtermInterrupt,
    StandardOutputError,
    bars_as_log_lines,
    drop_unwritten_output,
    missing_streams_to_devnull,
    show_warning,
    standard_output_errors,
    terminated_like_interrupted,
)
from warptex.cli.options import check_max_size_option
from warptex.cli.parsing import SUBCOMMANDS, build_parser, parse_arguments
from warptex.exemplar import ExemplarError
from warptex.stops import deferred_stops, started, stops_ignored_after_the_work
from warptex.warp_runtime import KernelCacheError, kernel_build_notice, say_kernel_build


def _check_device() -> None:
    """A device asked for through the environment that cannot be had, or a kernel cache
    folder (WARP_CACHE_PATH) that Warp cannot make as it starts, is a user error."""
    from warptex.warp_runtime import device, init_warp

    try:
        init_warp()
    except OSError as error:
        where = error.filename or os.environ.get("WARP_CACHE_PATH", "Warp's kernel cache")
        raise CliError(f"{where}: Warp cannot make its kernel cache there "
                       f"({error.strerror or error}); WARP_CACHE_PATH sets its folder") from None
    if os.environ.get("WARPTEX_DEVICE", "").strip():
        try:
            device()
        except (ValueError, RuntimeError) as error:
            raise CliError(str(error)) from None


# Libraries whose imports would lose a Ctrl-C or SIGTERM (trimesh's optional imports catch
# every exception), imported by the commands that use them before any work, stops held
# back until they are in.
_STOP_LOSING_LIBRARIES = {"bake": ("trimesh",), "cut": ("trimesh",)}


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``warptex`` with ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    missing_streams_to_devnull()
    code = _run(sys.argv[1:] if argv is None else list(argv))
    stops_ignored_after_the_work()
    return code


def _run(argv: list[str]) -> int:
    WRITTEN.clear()
    args = parse_arguments(build_parser(), argv)  # SciPy and more load here, Ctrl-C quiet
    _, command = SUBCOMMANDS[args.command]
    with (warnings.catch_warnings(), terminated_like_interrupted(), bars_as_log_lines(),
          standard_output_errors()):
        warnings.showwarning = show_warning
        try:
            started()  # Ctrl-C is a KeyboardInterrupt again, which the excepts below end
            if "exemplar_max_size" in args:  # before any work, a mesh's loading included
                check_max_size_option(args)
            if args.command not in ("info", "cache"):  # the two that use no device
                _check_device()
            with deferred_stops():
                for library in _STOP_LOSING_LIBRARIES.get(args.command, ()):
                    importlib.import_module(library)
            with kernel_build_notice(say_kernel_build):
                code = command(args)
            sys.stdout.flush()  # here, so that a reader gone early is handled below
            return code
        except BrokenPipeError:  # `warptex info ... | head -1`: the reader has all it wants
            drop_unwritten_output()
            return 141  # as for a command that SIGPIPE ends
        except (ExemplarError, CliError) as error:
            print(f"warptex: error: {error}", file=sys.stderr)
            return error.exit_code if isinstance(error, CliError) else 2
        except (KernelCacheError, StandardOutputError) as error:  # the machine's, mid-work
            if isinstance(error, StandardOutputError):
                drop_unwritten_output()
            # Standard output may fail on the line that says an output was written.
            print(f"warptex: error: {error}{_written_aside()}", file=sys.stderr)
            return 1
        except (MemoryError, RuntimeError) as error:
            if not _out_of_memory(error):
                raise
            # The checks before the work estimate; a limit they did not see, or work beyond
            # the estimate, fails an allocation anywhere (a NumPy array, a Warp array).
            print(f"warptex: error: out of memory ({str(error) or 'MemoryError'}): the work "
                  "needs more than this machine, or this process's memory limit, allows; ask "
                  f"for less of it{_written_aside()}", file=sys.stderr)
            return 1
        except KeyboardInterrupt as stop:  # outputs are renamed into place whole: none partial
            terminated = isinstance(stop, SigtermInterrupt) or SIGTERM_RECEIVED.is_set()
            print(f"\nwarptex: {'terminated' if terminated else 'interrupted'}{_after_writing()}",
                  file=sys.stderr)
            return 143 if terminated else 130  # as for a command that the signal ends


def _out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is a failed allocation: NumPy's MemoryError, or Warp's RuntimeError
    for an array it could not allocate."""
    return isinstance(error, MemoryError) or str(error).startswith("Failed to allocate")


def _written_aside() -> str:
    """:func:`_after_writing` in brackets, after an error's own words; none before any."""
    return f" ({_after_writing().strip()})" if WRITTEN else ""


def _after_writing() -> str:
    """The words " after writing A, B" of the outputs written so far; none before any."""
    return "" if not WRITTEN else " after writing " + ", ".join(
        str(f) for f in dict.fromkeys(WRITTEN))
