"""One owner per folder: the folder lock is an operating-system lock (``flock``).

The lock of :class:`experiments.evaluation.storage.FolderLock` is released by the kernel
when its owner ends, so no stale lock is ever taken over and processes trying at once
cannot both win: 6 contender processes race for each of 250 folders (5 x 50) that hold the
lock file of a dead run (where the old takeover of stale locks raced: two owners in about 1
trial of 100), and every folder gets exactly one owner. A lock file naming a live process
that holds no lock (a pid reused, another program) does not block; the lock of a run killed
with SIGKILL is free at once.
"""

from __future__ import annotations

import multiprocessing
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

CONTENDERS = 6
TRIALS = 250  # 5 x 50
JITTER = 0.0005  # [s] largest delay of a contender after the start signal


def contend(folders: list[str], barrier, results, index: int) -> None:
    """One contender: at each folder, all together, try to take its lock and report; hold
    it until every contender has tried, then release it."""
    from experiments.evaluation.storage import FolderLock, ResultsFolderError

    rng = random.Random(index)
    for trial, folder in enumerate(folders):
        barrier.wait()
        start = time.perf_counter() + rng.uniform(0.0, JITTER)  # (spreads the attempts)
        while time.perf_counter() < start:
            pass
        try:
            lock = FolderLock(Path(folder)).acquire()
        except ResultsFolderError:
            lock = None
        results.put((trial, index, lock is not None))
        barrier.wait()
        if lock is not None:
            lock.release()


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_six_contenders_never_both_own_a_folder(tmp_path) -> None:
    """Case 9: the stale-lock takeover raced (here: 2 owners in 1 to 5 of 250 trials).
    Now 250 trials of 6 contenders give exactly one owner each."""
    stale = f"{dead_pid()} {socket.gethostname()}\n"
    folders = []
    for trial in range(TRIALS):
        folder = tmp_path / f"out{trial}"
        folder.mkdir()
        (folder / ".lock").write_text(stale)  # left by a run that was killed
        folders.append(str(folder))
    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(CONTENDERS, timeout=120), ctx.Queue()
    procs = [
        ctx.Process(target=contend, args=(folders, barrier, results, i)) for i in range(CONTENDERS)
    ]
    for p in procs:
        p.start()
    try:
        reports = [results.get(timeout=180) for _ in range(CONTENDERS * TRIALS)]
    finally:
        for p in procs:
            p.join(timeout=60)
            if p.is_alive():
                p.kill()
    assert [p.exitcode for p in procs] == [0] * CONTENDERS
    owners = [0] * TRIALS
    for trial, _, owned in reports:
        owners[trial] += owned
    double = {t: n for t, n in enumerate(owners) if n != 1}
    assert not double, f"trials with other than one owner (trial: owners): {double}"
    for folder in folders:  # every owner released its lock
        assert not (Path(folder) / ".lock").exists()


def test_a_lock_file_naming_a_live_process_that_holds_no_lock_does_not_block(tmp_path) -> None:
    """Case 9: a lock file naming a live unrelated process (its pid reused) blocked the
    folder for ever. The file is not the lock: the folder is free."""
    from experiments.evaluation.storage import FolderLock

    (tmp_path / ".lock").write_text(f"{os.getppid()} {socket.gethostname()}\n")
    lock = FolderLock(tmp_path).acquire()
    assert (tmp_path / ".lock").read_text() == f"{os.getpid()} {socket.gethostname()}\n"
    lock.release()
    assert not (tmp_path / ".lock").exists()


HOLD = """
import sys, time
from pathlib import Path
from experiments.evaluation.storage import FolderLock
FolderLock(Path(sys.argv[1])).acquire()
print("held", flush=True)
time.sleep(600)
"""


def test_the_lock_of_a_killed_owner_is_free_at_once_and_a_live_one_is_named(tmp_path) -> None:
    from experiments.evaluation.storage import FolderLock, ResultsFolderError

    owner = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert owner.stdout.readline().strip() == "held"
        with pytest.raises(ResultsFolderError, match=rf"in use by process {owner.pid} on "):
            FolderLock(tmp_path).acquire()
    finally:
        owner.send_signal(signal.SIGKILL)
        owner.wait()
    assert (tmp_path / ".lock").exists()  # left behind, but no longer a lock
    with FolderLock(tmp_path):
        with pytest.raises(ResultsFolderError, match=r"lock file .*\.lock"):
            FolderLock(tmp_path).acquire()
    assert not (tmp_path / ".lock").exists()
