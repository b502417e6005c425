"""The candidate cache folder: ``warptex cache`` lists its files and prunes those that no
run of this warptex reads, and never one that it reads."""

from __future__ import annotations

import json
import os
import shutil
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from warptex import candidate_cache as cc
from warptex import candidate_set, candidates
from warptex.candidate_set import DEFAULT_PARAMS, CandidateCacheError, CandidateSet
from warptex.candidates import cache_path, precompute
from warptex.cli import main
from warptex.exemplar import Exemplar

GRANITE = Path(__file__).resolve().parent / "data" / "granite_64.png"


@pytest.fixture(scope="module")
def image(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("image") / "granite_16.png"
    Image.open(GRANITE).convert("RGB").crop((0, 0, 16, 16)).save(path)
    return path


@pytest.fixture(scope="module")
def computed(image, tmp_path_factory) -> tuple[Path, Path]:
    """A cache file of this warptex and one of other code (a warptex whose candidate
    code differs: same exemplar, same format, another name)."""
    folder = tmp_path_factory.mktemp("computed")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("WARPTEX_CACHE", str(folder))
        ex = Exemplar.load(image)
        precompute(ex)
        current = cache_path([ex, ex, ex], dict(DEFAULT_PARAMS))
        mp.setattr(candidates, "_code_digest", lambda: "the code of another version")
        precompute(ex)
        other = cache_path([ex, ex, ex], dict(DEFAULT_PARAMS))
    assert current.exists() and other.exists() and current != other
    return current, other


# Other tools' files in a shared cache folder, one named like a cache file but for its end.
_FOREIGN = ("notes.txt", "bunny.wtb", f"{candidates.CACHE_PREFIX}notes.txt")


@pytest.fixture
def folder(computed, tmp_path, monkeypatch) -> Path:
    """A cache folder holding one file of each kind, and files of other tools."""
    current, other = computed
    folder = tmp_path / "cache"
    folder.mkdir()
    shutil.copy(current, folder / current.name)
    shutil.copy(other, folder / other.name)
    data = current.read_bytes()
    at = len(candidate_set.FILE_MAGIC)
    older = data[:at] + (candidate_set.FORMAT_VERSION - 1).to_bytes(4, "little") + data[at + 4:]
    (folder / f"{candidates.CACHE_PREFIX}{'0' * 40}.wtc").write_bytes(older)
    (folder / f"{candidates.CACHE_PREFIX}{'1' * 40}.wtc").write_bytes(data[: len(data) // 2])
    (folder / f"{candidates.CACHE_PREFIX}{'2' * 40}.wtc").write_bytes(b"not candidates at all")
    unfinished = folder / f".{current.stem}.123.456.tmp.wtc"
    unfinished.write_bytes(data[:100])
    hours_ago = time.time() - 2 * cc.UNFINISHED_AGE
    os.utime(unfinished, (hours_ago, hours_ago))
    (folder / f".{current.stem}.789.1.tmp.wtc").write_bytes(data[:100])
    for name in _FOREIGN:
        (folder / name).write_text("another tool's file")
    monkeypatch.setenv("WARPTEX_CACHE", str(folder))
    return folder


def _statuses(folder: Path) -> dict[str, str]:
    return {f.path.name: f.status for f in cc.cache_files(folder)}


def test_reading_a_slow_cache_shows_a_bar(folder, monkeypatch, capsys):
    """Every file is read whole: a large cache took seconds with nothing shown (1 GB in
    4.9 s); a bar shows once reading takes over a second."""
    import time

    status = cc._status
    monkeypatch.setattr(cc, "_status", lambda path: (time.sleep(0.4), status(path))[1])
    assert cc.cache_files(folder, progress=True)
    assert "reading the cache" in capsys.readouterr().err


def test_cache_files_tell_each_kind_apart(folder, computed, image):
    current, other = computed
    files = {f.path.name: f for f in cc.cache_files(folder)}
    assert {name: f.status for name, f in files.items()} == {
        current.name: cc.IN_USE,
        other.name: cc.OTHER_VERSION,
        f"candidates-{'0' * 40}.wtc": cc.OTHER_VERSION,  # an older format
        f"candidates-{'1' * 40}.wtc": cc.DAMAGED,  # truncated
        f"candidates-{'2' * 40}.wtc": cc.DAMAGED,  # not a candidate file
        f".{current.stem}.123.456.tmp.wtc": cc.UNFINISHED,
        f".{current.stem}.789.1.tmp.wtc": cc.BEING_WRITTEN,
    }
    assert files[current.name].names == (image.name,) * 3
    # What another format's file was for, where it recorded it as this one does (the
    # listing called it "(not recorded)"); nothing of a damaged one.
    assert files[f"candidates-{'0' * 40}.wtc"].names == (image.name,) * 3
    assert files[f"candidates-{'1' * 40}.wtc"].names == ()
    assert files[current.name].size == current.stat().st_size
    assert [f.modified for f in files.values()] == sorted(f.modified for f in files.values())
    assert cc.cache_files(folder / "not yet made") == []


def test_cache_files_of_one_photo_loaded_otherwise_are_told_apart(image, tmp_path, monkeypatch,
                                                                  capsys):
    """Files of one photo with a feature-distance channel, shrunk, or of other parameters
    are listed with what sets each apart, not as rows of the same name."""
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path))
    precompute(Exemplar.load(image), progress=False)
    precompute(Exemplar.load(image, feature_distance=True), progress=False)
    mask = tmp_path / "mask.png"
    Image.fromarray((np.arange(16 * 16).reshape(16, 16) % 7 < 3).astype(np.uint8) * 255).save(mask)
    precompute(Exemplar.load(image, feature_mask=mask), progress=False)
    precompute(Exemplar.load(GRANITE, max_size=16), progress=False)
    precompute(Exemplar.load(image), tileable=True, progress=False)
    rgba = Image.open(image).convert("RGBA")
    rgba.putalpha(128)
    rgba.save(tmp_path / "rgba.png")
    precompute(Exemplar.load(tmp_path / "rgba.png", alpha="keep"), progress=False)
    listed = sorted((f.names[0], str(f.settings)) for f in cc.cache_files(tmp_path))
    assert listed == sorted([(image.name, "{}"),
                             (f"{image.name} (automatic feature distance)", "{}"),
                             (f"{image.name} (feature distance from mask.png)", "{}"),
                             ("granite_64.png (shrunk to 16x16)", "{}"),
                             (image.name, "{'tileable': True}"), ("rgba.png (4 channels)", "{}")])
    assert main(["cache"]) == 0
    out = capsys.readouterr().out
    assert "  granite_64.png (shrunk to 16x16)\n" in out
    assert f"  {image.name}; tileable=yes\n" in out
    assert main(["cache", "--json"]) == 0
    files = json.loads(capsys.readouterr().out)["files"]
    assert sorted(json.dumps(f["settings"]) for f in files) == ['{"tileable": true}'] + ["{}"] * 5


def test_a_set_of_three_exemplars_is_listed_by_axis(tmp_path, monkeypatch, capsys):
    """Candidates of one exemplar per axis (--ex, --ey, --ez) name each with its axis."""
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    granite = Image.open(GRANITE).convert("RGB")
    for name, (x, y) in (("a.png", (0, 0)), ("b.png", (16, 0)), ("c.png", (0, 16))):
        granite.crop((x, y, x + 16, y + 16)).save(tmp_path / name)
    precompute(*(Exemplar.load(tmp_path / f"{n}.png") for n in "abc"), progress=False)
    (listed,) = cc.cache_files(tmp_path / "cache")
    assert listed.status == cc.IN_USE and listed.names == ("a.png", "b.png", "c.png")
    assert main(["cache"]) == 0
    assert f"  {listed.path.name}  x a.png, y b.png, z c.png\n" in capsys.readouterr().out


def test_a_renamed_cache_file_is_never_read_and_listed_so(folder, computed):
    current, _ = computed
    renamed = folder / f"{candidates.CACHE_PREFIX}{'3' * 40}.wtc"
    shutil.copy(current, renamed)
    assert _statuses(folder)[renamed.name] == cc.OTHER_VERSION


def test_a_pipe_named_like_a_cache_file_is_listed_unreadable_not_waited_on(folder):
    """Reading a pipe would wait for a writer for ever (``warptex cache`` hung)."""
    import signal

    class Waited(BaseException):
        """No OSError (TimeoutError is one), which the listing would take for a status."""

    def waited(*_):
        raise Waited("waited for a writer of the pipe")

    pipe = folder / f"{candidates.CACHE_PREFIX}{'4' * 40}.wtc"
    os.mkfifo(pipe)
    before = signal.signal(signal.SIGALRM, waited)
    signal.alarm(30)
    try:
        assert _statuses(folder)[pipe.name] == cc.UNREADABLE
        with pytest.raises(CandidateCacheError, match="not a regular file"):
            CandidateSet.load(pipe)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)


def test_a_link_in_a_loop_named_like_a_cache_file_is_listed_unreadable(folder, computed):
    """Its stat() fails with ELOOP, which stopped the whole listing and --prune; a link
    through a file (ENOTDIR) did the same."""
    current, _ = computed
    loop = folder / f"{candidates.CACHE_PREFIX}{'5' * 40}.wtc"
    loop.symlink_to(loop.name)
    through_a_file = folder / f"{candidates.CACHE_PREFIX}{'6' * 40}.wtc"
    through_a_file.symlink_to(current / "inside")
    statuses = _statuses(folder)
    assert statuses[loop.name] == statuses[through_a_file.name] == cc.UNREADABLE
    assert statuses[current.name] == cc.IN_USE
    assert main(["cache", "--prune"]) == 0
    assert loop.is_symlink() and through_a_file.is_symlink() and current.exists()


def test_files_gone_between_the_listing_and_their_reading_are_left_out(folder, computed,
                                                                       monkeypatch):
    """Another run's prune meanwhile: a file gone before it is read, a link in a loop
    gone before it is looked at itself, are no longer there to list, and no error."""
    current, other = computed
    loop = folder / f"{candidates.CACHE_PREFIX}{'5' * 40}.wtc"
    loop.symlink_to(loop.name)
    status, lstat = cc._status, Path.lstat

    def pruned_before_read(path: Path):
        if path.name == other.name:
            path.unlink()
        return status(path)

    def pruned_before_lstat(self: Path):
        if self == loop:
            self.unlink()
        return lstat(self)

    monkeypatch.setattr(cc, "_status", pruned_before_read)
    monkeypatch.setattr(Path, "lstat", pruned_before_lstat)
    statuses = _statuses(folder)
    assert other.name not in statuses and loop.name not in statuses
    assert statuses[current.name] == cc.IN_USE and len(statuses) == 6


def test_a_cache_folder_whose_files_cannot_be_looked_up_is_refused_in_words(
        folder, monkeypatch, capsys):
    """A folder that may be listed but not searched (mode r--): none of its files can be
    looked up, which is said, not listed as an empty cache nor as a traceback; nothing is
    deleted."""
    stat = Path.stat
    before = sorted(os.listdir(folder))

    def unsearchable(self: Path, *args, **kwargs):
        if self.parent == folder:
            raise PermissionError(13, "Permission denied", str(self))
        return stat(self, *args, **kwargs)

    with monkeypatch.context() as patched:
        patched.setattr(Path, "stat", unsearchable)
        assert main(["cache", "--prune"]) == 2
    err = capsys.readouterr().err
    # The first of its cache or temporary files, whichever the folder lists first.
    assert err.startswith(f"warptex: error: {folder}{os.sep}") and candidates.CACHE_PREFIX in err
    assert err.endswith(": cannot list the candidate cache (Permission denied); "
                        "WARPTEX_CACHE sets its folder\n")
    assert sorted(os.listdir(folder)) == before


def _rewritten(source: Path, target: Path, meta: dict | None = None, **arrays) -> None:
    """``source``'s candidate file written, checksummed, at ``target`` with ``meta`` and
    ``arrays`` changed: a file made by other means, which the checksum does not tell."""
    from warptex.archive import read_archive, write_archive

    stored = read_archive(source, candidate_set.FILE_MAGIC, candidate_set.FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    if meta is not None:
        record = json.loads(bytes(stored["meta"]).decode())
        stored["meta"] = np.frombuffer(json.dumps({**record, **meta}).encode(), np.uint8)
    write_archive(target, candidate_set.FILE_MAGIC, candidate_set.FORMAT_VERSION,
                  {**stored, **arrays})


def test_a_file_that_runs_refuse_is_listed_damaged_not_in_use(folder, computed, image,
                                                              capsys):
    """The listing and ``info`` read the checksum, the key and the code, not whether the
    arrays fit together: a file every run refused as damaged was listed "in use" and never
    pruned. A record's names of another type stopped the listing with a TypeError."""
    from warptex.candidates import cached_candidate_path

    current, _ = computed
    arrays = CandidateSet.load(current)
    finest = arrays.num_levels - 1
    cand = arrays.roles[finest][0].cand.astype(np.int64) + 60000
    _rewritten(current, current.with_name("beyond"), **{f"L{finest}/R0/cand": cand})
    os.replace(current.with_name("beyond"), folder / current.name)
    names = folder / f"{candidates.CACHE_PREFIX}{'6' * 40}.wtc"
    _rewritten(current, names, meta={"names": 5})
    statuses = _statuses(folder)
    assert statuses[current.name] == statuses[names.name] == cc.DAMAGED
    assert cached_candidate_path(Exemplar.load(image)) is None
    assert main(["cache"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert main(["cache", "--prune"]) == 0
    assert not (folder / current.name).exists() and not names.exists()


def test_a_file_of_another_format_whose_record_cannot_be_read_is_listed_without_names(
        folder, computed, capsys):
    """An older format's whole file whose record is no record this version reads (it
    lacks what names a file, or is no JSON): another version's file, of exemplars not
    recorded, not a listing stopped by its error."""
    from warptex.archive import read_archive, write_archive

    current, _ = computed
    older = candidate_set.FORMAT_VERSION - 1
    stored = read_archive(current, candidate_set.FILE_MAGIC, candidate_set.FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    records = {"7": json.dumps({"names": ["granite_16.png"] * 3}).encode(), "8": b"{not json"}
    paths = {}
    for digit, record in records.items():
        paths[digit] = folder / f"{candidates.CACHE_PREFIX}{digit * 40}.wtc"
        write_archive(paths[digit], candidate_set.FILE_MAGIC, older,
                      {**stored, "meta": np.frombuffer(record, np.uint8)})
    with pytest.raises(CandidateCacheError, match=r"7{40}\.wtc: unreadable candidate data "
                       r"\('digests, params'\)"):
        candidate_set.read_cache_meta(paths["7"], older)
    listed = {f.path.name: f for f in cc.cache_files(folder)}
    for path in paths.values():
        assert (listed[path.name].status, listed[path.name].names) == (cc.OTHER_VERSION, ())
    assert main(["cache"]) == 0
    out, err = capsys.readouterr()
    assert all(f"  {path.name}  (not recorded)\n" in out for path in paths.values())
    assert "Traceback" not in err


def test_unreadable_and_replaced_files_are_left_alone(folder, computed):
    """A folder named like a cache file is listed, never deleted; a damaged file that another
    run replaced after the listing (recomputed candidates) is not the file judged."""
    current, _ = computed
    odd = folder / f"{candidates.CACHE_PREFIX}{'4' * 40}.wtc"
    odd.mkdir()
    listed = {f.path.name: f for f in cc.cache_files(folder)}
    assert listed[odd.name].status == cc.UNREADABLE
    damaged = folder / f"{candidates.CACHE_PREFIX}{'1' * 40}.wtc"
    assert listed[damaged.name].status == cc.DAMAGED
    replaced = folder / ".replacement"
    shutil.copy(current, replaced)
    os.replace(replaced, damaged)  # as write_atomically puts a recomputed file in place
    never = [f for f in listed.values() if f.status in cc.NEVER_READ]
    count, _, failed = cc.remove(never)
    assert failed == []
    assert count == len(never) - 1
    assert damaged.read_bytes() == current.read_bytes() and odd.is_dir()
    assert main(["cache", "--clear"]) == 0
    assert odd.is_dir()


def test_prune_deletes_what_no_run_reads_and_keeps_the_rest(folder, computed, image, capsys):
    current, _ = computed
    assert main(["cache"]) == 0
    out = capsys.readouterr().out
    assert f"candidate cache: {folder}" in out
    assert "7 files" in out
    assert "1 in use, 2 other version, 2 damaged, 1 unfinished, 1 being written" in out
    assert "warptex cache --prune deletes the 5 that no run of this warptex reads" in out
    assert f"{current.name}  granite_16.png" in out
    assert "Warp's kernel cache: " in out
    assert len(_statuses(folder)) == 7  # listing deletes nothing

    assert main(["cache", "--prune"]) == 0
    assert "deleted: 5 files" in capsys.readouterr().out
    assert _statuses(folder) == {current.name: cc.IN_USE,
                                 f".{current.stem}.789.1.tmp.wtc": cc.BEING_WRITTEN}
    assert all((folder / name).exists() for name in _FOREIGN)
    again = precompute(Exemplar.load(image))
    assert again.cache_status == "loaded"
    assert again.names == (image.name,) * 3


def test_a_kernel_cache_that_cannot_be_listed_is_refused_before_anything_is_deleted(
        folder, monkeypatch, capsys):
    """It was looked up after the candidates were deleted: exit 2, "refused before any
    work", with the files gone and no line saying so."""
    from warptex import warp_runtime

    def unlistable():
        raise NotADirectoryError(20, "Not a directory", "bad.png")

    monkeypatch.setattr(warp_runtime, "stale_kernel_builds", unlistable)
    before = _statuses(folder)
    assert main(["cache", "--prune"]) == 2
    assert capsys.readouterr().err.endswith(
        "warptex: error: bad.png: cannot list Warp's kernel cache (Not a directory); "
        "WARP_CACHE_PATH sets its folder\n")
    assert _statuses(folder) == before


def test_a_kernel_build_that_cannot_be_deleted_fails_the_prune(folder, tmp_path, monkeypatch,
                                                               capsys):
    """A read-only kernel cache: its builds were skipped, "deleted: 0", exit 0."""
    import warp as wp

    kernels = tmp_path / "kernels"
    build = kernels / "wp_kernels.synthesis_0000000"
    build.mkdir(parents=True)
    after = kernels / "wp_kernels.synthesis_1111111"  # tried too: its deletion is no other's
    after.mkdir()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(kernels))
    rename = Path.rename

    def read_only(self, target):
        if self == build:
            raise PermissionError(13, "Permission denied", str(self))
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", read_only)
    assert main(["cache", "--prune"]) == 1
    out, err = capsys.readouterr()
    assert err.endswith(f"warptex: error: {build}: cannot delete (Permission denied)\n")
    assert "deleted: 1 kernel builds" in out
    assert build.is_dir() and not after.exists()


def test_the_kernel_cache_s_size_after_a_prune_is_what_its_folder_holds(folder, tmp_path,
                                                                          monkeypatch, capsys):
    """Builds of another Warp version lie beside Warp's folder, whose size their deletion
    was taken from: -0.3 MiB."""
    import warp as wp

    kernels = tmp_path / "warp" / wp.config.version
    kernels.mkdir(parents=True)
    (kernels / "kept.bin").write_bytes(b"k" * 1000)
    old = tmp_path / "warp" / "1.18.0" / "wp_kernels.bake_1234567"
    old.mkdir(parents=True)
    (old / "kernels.o").write_bytes(b"o" * 300_000)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(kernels))
    assert main(["cache", "--prune", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)["kernel_cache"]
    assert report["deleted"] == {"builds": 1, "bytes": 300_000}
    assert report["bytes"] == 1000 and not old.exists()


def test_a_kernel_cache_folder_that_does_not_exist_holds_no_builds(folder, tmp_path,
                                                                    monkeypatch, capsys):
    """Warp's kernel cache emptied, folder and all, since Warp started (it makes its folder
    on starting): nothing in it, no error, and no folder made by listing or pruning it."""
    import warp as wp

    missing = tmp_path / "warp" / wp.config.version
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(missing))
    assert main(["cache", "--prune"]) == 0
    out, err = capsys.readouterr()
    assert f"Warp's kernel cache: {missing} (WARP_CACHE_PATH sets it), 0.0 MiB;" in out
    assert "deleted: 0 kernel builds of other warptex or Warp versions" in out
    assert "deleted: 5 files" in out and err == ""
    assert not missing.parent.exists()


def test_a_warp_that_names_its_builds_otherwise_has_none_of_them_pruned(folder, tmp_path,
                                                                        monkeypatch, capsys):
    """A Warp without get_module_identifier names its builds in a way warptex cannot tell
    from other versions': every build would look like another version's, so none is
    deleted, the current one least of all."""
    import warp as wp

    kernels = tmp_path / "kernels"
    build = kernels / "wp_kernels.synthesis_0000000"
    build.mkdir(parents=True)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(kernels))
    monkeypatch.delattr(type(wp.get_module("kernels.synthesis")), "get_module_identifier")
    assert main(["cache", "--prune"]) == 0
    assert "deleted: 0 kernel builds" in capsys.readouterr().out
    assert build.is_dir()


def test_cache_json_lists_the_same_files_and_what_was_deleted(folder, computed, capsys):
    current, _ = computed
    assert main(["cache", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["candidate_cache"] == str(folder) and report["deleted"] is None
    statuses = {Path(f["file"]).name: f["status"] for f in report["files"]}
    assert statuses == {f.path.name: f.status for f in cc.cache_files(folder)}
    (entry,) = [f for f in report["files"] if Path(f["file"]).name == current.name]
    assert entry["status"] == cc.IN_USE and entry["bytes"] == current.stat().st_size
    assert [Path(n).name for n in entry["exemplars"]] == ["granite_16.png"] * 3
    assert datetime.strptime(entry["written"], "%Y-%m-%dT%H:%M:%SZ")
    assert report["kernel_cache"]["deleted"] is None and report["kernel_cache"]["folder"]
    assert main(["cache", "--prune", "--json"]) == 0
    pruned = json.loads(capsys.readouterr().out)
    assert pruned["deleted"]["files"] == 5 and pruned["kernel_cache"]["deleted"] is not None
    assert len(cc.cache_files(folder)) == 2


def test_clear_deletes_every_candidate_file_but_writes_in_progress(folder, image, capsys):
    assert main(["cache", "--clear"]) == 0
    assert "deleted: 6 files" in capsys.readouterr().out
    assert [f.status for f in cc.cache_files(folder)] == [cc.BEING_WRITTEN]
    assert all((folder / name).exists() for name in _FOREIGN)
    assert precompute(Exemplar.load(image)).cache_status == "written"


def test_a_missing_cache_folder_is_reported_and_not_made(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "nothing here"))
    assert main(["cache", "--prune"]) == 0
    out = capsys.readouterr().out
    assert "no candidate files" in out and "deleted: 0 files, 0.0 MiB" in out
    assert not (tmp_path / "nothing here").exists()


def test_a_cache_folder_that_is_a_file_is_one_clear_error(tmp_path, monkeypatch, capsys):
    path = tmp_path / "cache"
    path.write_text("a file")
    monkeypatch.setenv("WARPTEX_CACHE", str(path))
    assert main(["cache"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"warptex: error: {path}: ") and "WARPTEX_CACHE" in err
    assert "Traceback" not in err and path.read_text() == "a file"


def test_a_cache_folder_that_is_a_link_to_nowhere_is_named_not_listed_empty(
        tmp_path, monkeypatch, capsys):
    """A link to a missing folder (an unmounted disk) or a loop of links was listed as
    "no candidate files", though nothing could be cached there."""
    (tmp_path / "unmounted").symlink_to(tmp_path / "disk" / "cache")
    (tmp_path / "loop").symlink_to("loop")
    for folder, link, target in (("unmounted", "unmounted", tmp_path / "disk" / "cache"),
                                 ("unmounted/warptex", "unmounted", tmp_path / "disk" / "cache"),
                                 ("loop", "loop", "loop")):
        monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / folder))
        assert main(["cache"]) == 2
        assert capsys.readouterr().err == (
            f"warptex: error: {tmp_path / folder}: cannot list the candidate cache "
            f"({tmp_path / link} is a symbolic link to {target}, which leads nowhere); "
            "WARPTEX_CACHE sets its folder\n")


def test_a_file_that_cannot_be_deleted_is_named_and_the_others_are_deleted(
        folder, tmp_path, monkeypatch, capsys):
    """The first file that could not be deleted stopped the prune: the files after it and
    Warp's old kernel builds were left, and nothing was listed."""
    import warp as wp

    build = tmp_path / "kernels" / "wp_kernels.synthesis_0000000"
    build.mkdir(parents=True)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(build.parent))
    real_unlink = Path.unlink

    def refuse(self, missing_ok=False):
        if self.name.endswith("1" * 40 + ".wtc"):
            raise PermissionError(13, "Permission denied", str(self))
        real_unlink(self, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", refuse)
    assert main(["cache", "--prune"]) == 1  # a failure in the work, not bad input
    out, err = capsys.readouterr()
    assert err.endswith(f"{'1' * 40}.wtc: cannot delete (Permission denied)\n")
    left = _statuses(folder)
    assert left.pop(f"candidates-{'1' * 40}.wtc") == cc.DAMAGED
    assert sorted(left.values()) == sorted([cc.IN_USE, cc.BEING_WRITTEN])
    assert "deleted: 4 files" in out and "deleted: 1 kernel builds" in out
    assert not build.exists()


def test_names_are_kept_in_candidate_files(computed, image, tmp_path):
    current, _ = computed
    assert CandidateSet.load(current).names == (image.name,) * 3
    ex = Exemplar.load(image)
    path = tmp_path / "renamed.wtc"
    shutil.copy(image, tmp_path / "same pixels.png")
    same = precompute(Exemplar.load(tmp_path / "same pixels.png"), cache=False)
    same.save(path)
    loaded = CandidateSet.load(path)
    assert loaded.names == ("same pixels.png",) * 3
    assert loaded.content_digest == CandidateSet.load(current).content_digest
    assert loaded.digests == (ex.digest(),) * 3


def test_a_file_of_a_newer_format_is_listed_as_another_version(tmp_path, monkeypatch,
                                                               warp_device):
    """Written by a later warptex (format version + 1): another version's file, whole,
    not a damaged one."""
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path))
    ex = Exemplar(Exemplar.load(GRANITE).colors[:16, :16], name="crop")
    precompute(ex)
    (path,) = tmp_path.glob("candidates-*.wtc")
    data = path.read_bytes()
    at = len(candidate_set.FILE_MAGIC)
    newer = data[:at] + (candidate_set.FORMAT_VERSION + 1).to_bytes(4, "little") + data[at + 4:]
    (tmp_path / f"{candidates.CACHE_PREFIX}{'5' * 40}.wtc").write_bytes(newer)
    statuses = {f.path.name: f.status for f in cc.cache_files(tmp_path)}
    assert statuses[f"{candidates.CACHE_PREFIX}{'5' * 40}.wtc"] == cc.OTHER_VERSION
    assert statuses[path.name] == cc.IN_USE


def test_a_file_of_this_name_but_other_code_is_listed_as_other_code(folder, computed):
    """A current name does not make a file current: one whose record names other code
    (copied from another machine, renamed) is one every run refuses and recomputes."""
    current, _ = computed
    _rewritten(current, folder / current.name, meta={"code": "another warptex's code"})
    assert _statuses(folder)[current.name] == cc.OTHER_VERSION


def test_prune_reports_the_bytes_it_freed_and_leaves_young_writes(folder):
    """What --prune says it freed is the files' sizes; a temporary file younger than
    UNFINISHED_AGE (another run writing) is being written, not unfinished."""
    young = folder / f".{candidates.CACHE_PREFIX}{'7' * 40}.1.2.tmp.wtc"
    young.write_bytes(b"in progress")
    minutes_ago = time.time() - cc.UNFINISHED_AGE / 2
    os.utime(young, (minutes_ago, minutes_ago))
    assert _statuses(folder)[young.name] == cc.BEING_WRITTEN
    listed = [f for f in cc.cache_files(folder) if f.status in cc.NEVER_READ]
    count, freed, failed = cc.remove(listed)
    assert failed == [] and count == len(listed)
    assert freed == sum(f.size for f in listed) > 0


def test_a_file_rewritten_in_place_since_the_listing_is_left_alone(folder):
    """Rewritten in place at the same size (same inode), a file is told apart from the one
    listed by its modification time."""
    damaged = folder / f"{candidates.CACHE_PREFIX}{'1' * 40}.wtc"
    (listed,) = [f for f in cc.cache_files(folder) if f.path == damaged]
    data = damaged.read_bytes()
    with damaged.open("r+b") as file:
        file.write(bytes(len(data)))
    later = time.time() + 5
    os.utime(damaged, (later, later))
    assert cc.remove([listed])[0] == 0 and damaged.read_bytes() == bytes(len(data))


def test_a_file_another_prune_deleted_meanwhile_is_no_failure(folder, monkeypatch):
    """Two prunes at once: a file the other deleted after the listing is skipped, not
    counted as one that could not be deleted."""
    listed = [f for f in cc.cache_files(folder) if f.status in cc.NEVER_READ]

    def gone(self, missing_ok=False):
        raise FileNotFoundError(self)

    monkeypatch.setattr(Path, "unlink", gone)
    assert cc.remove(listed) == (0, 0, [])


def test_a_file_pruned_while_it_is_read_is_computed_again_unsaid(computed, image, tmp_path,
                                                                  monkeypatch):
    """`warptex cache --clear` beside a render node: the file gone between its lookup and
    its read was called damaged, sending an operator looking for corruption."""
    import warnings

    current, _ = computed
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path))
    shutil.copy(current, tmp_path / current.name)
    there = candidates.cache_file_there

    def pruned_meanwhile(path: Path) -> bool:
        found = there(path)
        monkeypatch.setattr(candidates, "cache_file_there", there)
        path.unlink()
        return found

    monkeypatch.setattr(candidates, "cache_file_there", pruned_meanwhile)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert precompute(Exemplar.load(image)).cache_status == "written"
    assert (tmp_path / current.name).read_bytes() == current.read_bytes()


def test_a_file_whose_record_names_no_code_is_not_this_code_s(computed):
    """Only a record naming this code's digest is this code's: one naming none (written by
    other means) is recomputed, never read."""
    assert candidates.computed_here({"code": candidates._code_digest()})
    assert not candidates.computed_here({})
    assert not candidates.computed_here({"code": None})
