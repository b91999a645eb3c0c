"""The C library cache can be trusted: a damaged, foreign or planted library is never loaded.

Each case is a real file in a real cache folder (``$LFM_CACHE_DIR`` of the test) and a real
build in a process of its own (:mod:`tests.controllers.solvers.fast.cache_runs`), so a
library that crashes the process that loads it fails the test instead of ending the suite:

* a truncated library (``truncate -s 4096``) is rebuilt with a one-line notice naming it;
* another system's library copied under the key (with or without its record) is rebuilt,
  and the merits are the NumPy backend's;
* a library planted in a folder others can write, or a planted file of another user or
  writable by others, is never loaded: its constructor (which writes a marker file) never
  runs, a warning names it, and the build goes to a private folder removed at exit;
* the key covers the compiler: a library built with ``CC="cc -O0"`` is not reused by the
  default compiler, nor by an upgraded compiler (a wrapper script changed);
* a failed build is not tried again in the same process, and the NumPy fallback is
  announced once; an unusable cache folder gives one private folder, removed at exit.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from controllers.solvers.fast.codegen import build
from controllers.solvers.fast.condensed import CondensedModel
from experiments.benchmark.problems import problem_from_config

ROOT = Path(__file__).resolve().parents[4]
RTOL = 1e-12


@pytest.fixture(scope="module")
def paper():
    return problem_from_config(n_scenarios=20)


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch) -> Path:
    """An empty cache folder for this process (and no library loaded; restored after)."""
    monkeypatch.setenv("LFM_CACHE_DIR", str(tmp_path / "cache"))
    build.forget_loaded()
    yield tmp_path / "cache"
    build.forget_loaded()


def run_build(cache: Path, which: str = "paper", builds: int = 1, **env: str):
    """A build of ``which`` in its own process with ``cache`` as the cache folder: the
    process and its JSON result (``None`` when it printed none, e.g. it crashed)."""
    full = {**os.environ, "LFM_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT), **env}
    full.pop("LFM_BACKEND", None)
    cmd = [sys.executable, "-m", "tests.controllers.solvers.fast.cache_runs", which, str(builds)]
    proc = subprocess.run(cmd, cwd=ROOT, env=full, capture_output=True, text=True, timeout=600)
    lines = proc.stdout.strip().splitlines()
    return proc, (json.loads(lines[-1]) if proc.returncode == 0 and lines else None)


def warnings_of(proc) -> list[str]:
    return [line for line in proc.stderr.splitlines() if line.startswith("warning:")]


def assert_correct(proc, result) -> None:
    """The build ran to its end with the compiled library, whose merit is NumPy's."""
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert result["backend"] == "compiled-c"
    assert result["merit"] == pytest.approx(result["reference"], rel=RTOL)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, dict[str, dict]]:
    """A cache folder holding the libraries of both systems, built once for the module,
    and each build's result."""
    cache = tmp_path_factory.mktemp("built") / "cache"
    results = {}
    for which in ("paper", "point_mass"):
        proc, results[which] = run_build(cache, which)
        assert_correct(proc, results[which])
    return cache, results


def copy_of(built, tmp_path: Path) -> tuple[Path, dict[str, Path]]:
    """A copy of the built cache folder in ``tmp_path`` and each system's library in it."""
    template, results = built
    cache = tmp_path / "cache"
    shutil.copytree(template, cache)
    return cache, {w: cache / Path(r["path"]).name for w, r in results.items()}


def test_a_truncated_library_is_rebuilt_with_a_notice(built, tmp_path) -> None:
    """Case 1: ``truncate -s 4096`` of the cached library made every later run die of
    SIGBUS; now it is found damaged, named once and built again."""
    cache, libraries = copy_of(built, tmp_path)
    library = libraries["paper"]
    os.truncate(library, 4096)
    proc, second = run_build(cache)
    assert_correct(proc, second)
    assert second["cache_hits"] == [False]  # built again
    (warning,) = warnings_of(proc)
    assert str(library) in warning and "damaged" in warning
    assert library.stat().st_size > 4096
    proc, third = run_build(cache)  # the rebuilt library serves, silently
    assert_correct(proc, third)
    assert third["cache_hits"] == [True] and not warnings_of(proc)


@pytest.mark.parametrize("copied", ["library", "library_and_record"])
def test_another_systems_library_under_the_key_is_rebuilt(copied, built, tmp_path) -> None:
    """Case 2: another system's library copied over the name (with its record too) aborted
    the run or gave wrong merits; now it is refused before it is loaded and rebuilt."""
    cache, libraries = copy_of(built, tmp_path)
    target, source = libraries["paper"], libraries["point_mass"]
    shutil.copyfile(source, target)
    if copied == "library_and_record" and source.with_suffix(".json").exists():
        shutil.copyfile(source.with_suffix(".json"), target.with_suffix(".json"))
    proc, again = run_build(cache, "paper")
    assert_correct(proc, again)
    assert again["merit"] == pytest.approx(built[1]["paper"]["merit"], rel=RTOL)
    assert again["cache_hits"] == [False]
    (warning,) = warnings_of(proc)
    assert str(target) in warning


EVIL = r"""
#include <stdio.h>
__attribute__((constructor)) static void planted(void) {
  FILE *f = fopen(MARKER, "w");
  if (f) { fputs("the planted library ran", f); fclose(f); }
}
int lfm_rollout(void) { return 0; }
"""


def plant(tmp_path: Path, folder: Path, name: str, marker: Path) -> Path:
    """A library whose constructor writes ``marker``, at ``folder/name``, with a record
    that matches it (an attacker who can write the folder can write both)."""
    c_file = tmp_path / "planted.c"
    c_file.write_text(EVIL)
    path = folder / name
    subprocess.run(
        ["cc", "-shared", "-fPIC", f'-DMARKER="{marker}"', str(c_file), "-o", str(path)],
        check=True,
    )
    key = path.stem.rpartition("_")[2]
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    path.with_suffix(".json").write_text(json.dumps({"key": key, "sha256": digest}))
    return path


PLANTS = ["folder_writable_by_others", "file_writable_by_others", "file_of_another_user"]


@pytest.mark.parametrize("how", PLANTS)
def test_a_planted_library_is_never_loaded(how, built, tmp_path) -> None:
    """Case 3: a library planted under the predictable name, in a folder others can write
    (or a file of another user, or one others can write) had its constructor run as the
    user who evaluates. Now no code of it runs: a warning names it, and the library is
    built and used (in a private folder, removed at exit, when the folder is refused)."""
    if how == "file_of_another_user" and os.geteuid() != 0:
        pytest.skip("giving a file to another user needs root")
    name = Path(built[1]["paper"]["path"]).name  # the library's name, here and now
    cache = tmp_path / "attacked"
    cache.mkdir(mode=0o700)
    marker = tmp_path / "marker"
    planted = plant(tmp_path, cache, name, marker)
    if how == "folder_writable_by_others":
        cache.chmod(0o777)
    elif how == "file_writable_by_others":
        planted.chmod(0o777)
    else:
        os.chown(planted, 65534, 65534)
    proc, result = run_build(cache)
    assert not marker.exists(), "the planted library's constructor ran"
    assert_correct(proc, result)
    (warning,) = warnings_of(proc)
    if how == "folder_writable_by_others":
        assert str(cache) in warning and "writable by other users" in warning
        assert Path(result["path"]).parent != cache
        assert not Path(result["path"]).parent.exists()  # the private folder: removed
    else:
        assert str(planted) in warning
        assert "another user" in warning or "not by you" in warning or "writable" in warning
        assert Path(result["path"]) == planted  # built again in its place
    assert not marker.exists()


def test_the_key_covers_the_compiler(paper, fresh_cache, tmp_path, monkeypatch) -> None:
    """Case 4: a library built with ``CC="cc -O0"`` was reused by a default-compiler run.
    Now the key covers the compiler's command and its executable (an upgraded compiler,
    here a wrapper script that changed, builds anew); the same compiler hits the cache."""
    monkeypatch.setenv("CC", "cc -O0")
    slow = CondensedModel(paper, backend="c")
    assert not slow.cache_hit
    build.forget_loaded()
    monkeypatch.delenv("CC")
    default = CondensedModel(paper, backend="c")
    assert not default.cache_hit  # compiled for its own compiler
    assert len(list(fresh_cache.glob("*.so"))) == 2
    build.forget_loaded()
    monkeypatch.setenv("CC", "cc -O0")
    assert CondensedModel(paper, backend="c").cache_hit  # the same compiler: reused
    wrapper = tmp_path / "cc-wrapper"
    wrapper.write_text('#!/bin/sh\nexec cc "$@"\n')
    wrapper.chmod(0o755)
    monkeypatch.setenv("CC", str(wrapper))
    build.forget_loaded()
    assert not CondensedModel(paper, backend="c").cache_hit
    wrapper.write_text('#!/bin/sh\n# upgraded\nexec cc "$@"\n')
    build.forget_loaded()
    assert not CondensedModel(paper, backend="c").cache_hit
    assert len(list(fresh_cache.glob("*.so"))) == 4


def counting_compiler(tmp_path: Path, fails: bool) -> tuple[Path, Path]:
    """A real cc behind a script that logs each call (and, with ``fails``, fails as on a
    full disk): the script and its log."""
    log = tmp_path / "calls.log"
    script = tmp_path / "cc-counting"
    body = (
        'echo "cc: fatal error: No space left on device" >&2; exit 1' if fails else 'exec cc "$@"'
    )
    script.write_text(f'#!/bin/sh\necho "$@" >> "{log}"\n{body}\n')
    script.chmod(0o755)
    return script, log


def calls(log: Path) -> int:
    return len(log.read_text().splitlines()) if log.exists() else 0


def test_a_failed_build_is_not_tried_again_and_the_fallback_is_announced_once(
    paper, fresh_cache, tmp_path, monkeypatch, capfd
) -> None:
    """Case 5: a build failing (here as on a full disk) was tried again for every agent
    built (7 s per episode instead of 0.2 s), silently. Now the compiler runs for the
    first build only (once per flag set of BUILDS), and one line announces the fallback."""
    script, log = counting_compiler(tmp_path, fails=True)
    monkeypatch.setenv("CC", str(script))
    capfd.readouterr()
    models = [CondensedModel(paper) for _ in range(3)]
    assert {m.backend for m in models} == {"numpy-lanes"}
    assert all("No space left on device" in m.backend_error for m in models)
    assert calls(log) == len(build.BUILDS)
    with pytest.raises(build.CodegenUnavailable, match="No space left"):
        CondensedModel(paper, backend="c")
    assert calls(log) == len(build.BUILDS)
    announced = [line for line in capfd.readouterr().err.splitlines() if "NumPy" in line]
    assert len(announced) == 1 and announced[0].startswith("warning: ")


def test_the_cache_serves_a_second_build_without_compiling(
    paper, fresh_cache, tmp_path, monkeypatch
) -> None:
    script, log = counting_compiler(tmp_path, fails=False)
    monkeypatch.setenv("CC", str(script))
    first = CondensedModel(paper)
    assert first.backend == "compiled-c" and not first.cache_hit
    n = calls(log)
    assert n >= 1
    build.forget_loaded()
    second = CondensedModel(paper)
    assert second.backend == "compiled-c" and second.cache_hit
    assert calls(log) == n  # no compiler ran
    assert CondensedModel(paper).cache_hit  # and within the process, from memory


def test_an_unusable_cache_folder_gives_one_private_folder_removed_at_exit(tmp_path) -> None:
    """Case 5: an unusable cache folder made a new temporary folder per build, never
    deleted. Now one private folder per process (with one warning), removed at exit."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder's parent should be")
    temp = tmp_path / "tmp"
    temp.mkdir()
    proc, result = run_build(blocker / "cache", "paper", 3, TMPDIR=str(temp))
    assert_correct(proc, result)
    assert result["cache_hits"] == [False, True, True]  # one private folder, reused
    (warning,) = warnings_of(proc)
    assert str(blocker / "cache") in warning
    assert not list(temp.iterdir())  # removed at exit


def test_a_full_disk_falls_back_once_and_leaves_nothing(tmp_path) -> None:
    """Case 5 on a real full disk: the cache folder and the temporary folder on a tmpfs of
    64 kB (a private mount namespace, root only) leave a NumPy fallback announced once,
    and nothing behind."""
    unshare = shutil.which("unshare")
    if os.geteuid() != 0 or unshare is None:
        pytest.skip("mounting a small tmpfs needs root and unshare")
    disk = tmp_path / "disk"
    disk.mkdir()
    probe = subprocess.run(
        [unshare, "-m", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {disk}"],
        capture_output=True,
    )
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {probe.stderr.decode().strip()}")
    run = (
        f"mount -t tmpfs -o size=64k tmpfs {disk} && mkdir {disk}/tmp && "
        f"{sys.executable} -m tests.controllers.solvers.fast.cache_runs paper 3; "
        f"echo left: $(ls -A {disk}/tmp | wc -l) $(ls -A {disk}/cache | grep -c so)"
    )
    env = {**os.environ, "LFM_CACHE_DIR": f"{disk}/cache", "TMPDIR": f"{disk}/tmp"}
    env["PYTHONPATH"] = str(ROOT)
    env.pop("LFM_BACKEND", None)
    proc = subprocess.run(
        [unshare, "-m", "sh", "-c", run], cwd=ROOT, env=env, capture_output=True, text=True
    )
    lines = proc.stdout.strip().splitlines()
    assert lines[-1] == "left: 0 0", proc.stderr[-2000:]
    result = json.loads(lines[-2])
    assert result["backend"] == "numpy-lanes"
    announced = [line for line in proc.stderr.splitlines() if "NumPy" in line]
    assert len(announced) == 1, proc.stderr
