"""``warptex cache``: the candidate cache and Warp's kernel cache, listed and pruned."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from warptex.archive import iso_date
from warptex.cli.common import CliError, WorkFailed


def add_cache_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "cache", help="list the candidate cache; prune the files this version never reads",
        description="List the candidate cache (WARPTEX_CACHE, default $XDG_CACHE_HOME/warptex "
        "where that is an absolute path, else ~/.cache/warptex): "
        "each file's date, size, exemplars and status. 'in use': read whenever its "
        "exemplars come up. 'other version': written by another warptex version, or "
        "under other versions of Warp, NumPy or SciPy (or renamed), which this one never "
        "reads. 'damaged': truncated or corrupt, computed "
        "again when needed. 'unfinished': left by a write that died over an hour ago. "
        "'being written': a write of another run, perhaps still going. 'unreadable': not "
        "readable here (another user's file, a folder), left alone. Files stay until "
        "deleted here. Also says where Warp's kernel cache is, how large, and how much of it "
        "holds builds of other warptex or Warp versions.",
        epilog="Deleted candidates are computed again when next needed (a few seconds for a "
        "64 px exemplar, about a minute for 256 px, minutes with one per axis).",
    )
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--prune", action="store_true",
                      help="delete the 'other version', 'damaged' and 'unfinished' files, "
                      "and Warp's builds of other versions of warptex's kernels")
    what.add_argument("--clear", action="store_true",
                      help="delete every candidate file but those 'being written' or "
                      "'unreadable', and what --prune deletes of Warp's kernel cache")
    parser.add_argument("--json", action="store_true",
                        help="print the listing (and what was deleted) as one JSON object")


def run_cache(args: argparse.Namespace) -> int:
    from warptex import candidate_cache as cc

    folder = cc.cache_dir()
    try:
        files = cc.cache_files(folder, progress=True)
    except OSError as error:
        raise CliError(f"{error.filename or folder}: cannot list the candidate cache "
                       f"({error.strerror or error}); WARPTEX_CACHE sets its folder") from None
    never = [f for f in files if f.status in cc.NEVER_READ]
    kept = (cc.BEING_WRITTEN, cc.UNREADABLE)
    doomed = [f for f in files if f.status not in kept] if args.clear else never
    kernels = _kernel_cache()  # refused here, before anything is deleted
    deleted = None
    undeleted: list[OSError] = []
    if args.prune or args.clear:  # each file and build tried, whatever the others did
        count, freed, undeleted = cc.remove(doomed)
        deleted = (count, freed)
        undeleted += _delete_kernel_builds(kernels)
    if args.json:
        print(json.dumps(_cache_report(folder, files, deleted, kernels), indent=2))
    else:
        _print_cache(folder, files, never, deleted, kernels)
    if undeleted:
        first = undeleted[0]
        others = f", and {len(undeleted) - 1} others" if len(undeleted) > 1 else ""
        raise WorkFailed(f"{first.filename}: cannot delete ({first.strerror or first})"
                         f"{others}")
    return 0


def _print_cache(folder: Path, files: list, never: list, deleted: tuple[int, int] | None,
                 kernels: dict) -> None:
    """``warptex cache``'s listing, and what it deleted."""
    from warptex import candidate_cache as cc

    print(f"candidate cache: {folder} (WARPTEX_CACHE sets it)")
    if files:
        print(f"  {'written':<16}  {'size':>9}  {'status':<13}  {'file':<55}  exemplars")
    for f in files:
        written = time.strftime("%Y-%m-%d %H:%M", time.localtime(f.modified))
        settings = "".join(f"; {_setting(k, v)}" for k, v in f.settings.items())
        print(f"  {written:<16}  {_mib_tenths(f.size):>9}  {f.status:<13}  {f.path.name:<55}  "
              f"{_exemplar_names(f.names)}{settings}")
    if not files:
        print("no candidate files")
    else:
        counts = ", ".join(f"{n} {status}" for status in cc.STATUSES
                           if (n := sum(f.status == status for f in files)))
        print(f"{len(files)} files, {_mib_tenths(sum(f.size for f in files))}: {counts}")
    if deleted is not None:
        print(f"deleted: {deleted[0]} files, {_mib_tenths(deleted[1])}")
    elif never:
        print(f"warptex cache --prune deletes the {len(never)} that no run of this warptex "
              f"reads ({_mib_tenths(sum(f.size for f in never))})")
    print(f"Warp's kernel cache: {kernels['folder']} (WARP_CACHE_PATH sets it), "
          f"{_mib_tenths(kernels['bytes'])}; built again when missing, so it may be emptied "
          "between runs")
    stale = kernels["other_builds"]
    if kernels["deleted"] is not None:
        print(f"deleted: {kernels['deleted']['builds']} kernel builds of other warptex or "
              f"Warp versions or left unfinished, {_mib_tenths(kernels['deleted']['bytes'])}")
    elif stale:
        print(f"  of which {len(stale)} kernel builds of other warptex or Warp versions or left "
              f"unfinished, {_mib_tenths(kernels['other_bytes'])}: warptex cache --prune "
              "deletes them")


def _cache_report(folder: Path, files: list, deleted: tuple[int, int] | None,
                  kernels: dict) -> dict:
    """``warptex cache --json``: the listing as data, times in ISO 8601 (UTC)."""
    return {
        "candidate_cache": str(folder),
        "files": [{"file": str(f.path), "written": iso_date(f.modified), "bytes": f.size,
                   "status": f.status, "exemplars": list(f.names),
                   "settings": f.settings} for f in files],
        "deleted": None if deleted is None else {"files": deleted[0], "bytes": deleted[1]},
        "kernel_cache": kernels,
    }


def _setting(name: str, value: object) -> str:
    """A candidate parameter as the command line gives it (``tileable=yes``)."""
    shown = ("yes" if value else "no") if isinstance(value, bool) else value
    return f"{name}={shown}"


def _exemplar_names(names: tuple[str, ...]) -> str:
    if not names:
        return "(not recorded)"
    short = [Path(n).name for n in names]
    if len(set(short)) == 1:
        return short[0]
    return ", ".join(f"{axis} {n}" for axis, n in zip("xyz", short, strict=False))


def _mib_tenths(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def _kernel_cache() -> dict:
    """Where Warp keeps the built kernels and how much they take, and the builds of
    warptex's kernels that no run of this version loads (every version builds its own, and
    Warp never deletes old ones); "deleted" is None until they are."""
    import warp as wp

    from warptex import warp_runtime

    try:
        stale = warp_runtime.stale_kernel_builds()
    except OSError as error:
        raise CliError(f"{error.filename}: cannot list Warp's kernel cache "
                       f"({error.strerror or error}); WARP_CACHE_PATH sets its folder") from None
    folder = Path(wp.config.kernel_cache_dir)
    return {"folder": str(folder), "bytes": warp_runtime.folder_bytes(folder),
            "other_builds": [str(f) for f in stale],
            "other_bytes": sum(warp_runtime.folder_bytes(f) for f in stale), "deleted": None}


def _delete_kernel_builds(kernels: dict) -> list[OSError]:
    """Delete the kernel builds :func:`_kernel_cache` found, entering how many and their
    bytes in ``kernels``, and the cache's size after; the errors of those left."""
    from warptex import warp_runtime

    count, freed, failed = warp_runtime.delete_kernel_builds(
        [Path(b) for b in kernels["other_builds"]])
    kernels["deleted"] = {"builds": count, "bytes": freed}
    kernels["bytes"] = warp_runtime.folder_bytes(Path(kernels["folder"]))
    return failed
