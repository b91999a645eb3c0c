"""The compiled SQP loop's interface has one source: ``codegen/interface.py``.

Its tables give the C header (``sqp_interface.h``: the options struct, the statuses and the
statistics), the ctypes mirror and the export's config; these tests fail when a side drifts:
a ``FastSolverOptions`` field that the C loop neither takes nor is told to ignore, a library
compiled from other tables, a hand-written copy of an index or a status name.
"""

from __future__ import annotations

import ctypes
import dataclasses
import re
from importlib import resources

from controllers.config import load_config
from controllers.solvers.fast.codegen import interface
from controllers.solvers.fast.codegen.source import c_source
from controllers.solvers.fast.compiled import STATS, STATUSES, sqp_library
from controllers.solvers.fast.options import FastSolverOptions


def test_every_option_is_a_c_field_or_named_python_only() -> None:
    fields = {f.name for f in dataclasses.fields(FastSolverOptions)}
    c_names = {o.name for o in interface.OPTIONS}
    assert fields - c_names == set(interface.PYTHON_ONLY)
    # every C field reads a FastSolverOptions field of its name or maps one
    defaults = FastSolverOptions()
    for option in interface.OPTIONS:
        assert option.name in fields or option.value is not None, option.name
        option.of(defaults)  # (raises on a missing field or choice)


def test_the_ctypes_mirror_and_the_header_come_from_the_same_table() -> None:
    text = interface.header()
    struct = text[text.index("typedef struct {") : text.index("} lfm_sqp_options;")]
    declared = re.findall(r"^\s+(long|double) (\w+);", struct, re.MULTILINE)
    mirrored = [
        ("long" if kind is ctypes.c_long else "double", name)
        for name, kind in interface.SqpOptions._fields_
    ]
    assert declared == mirrored
    assert [c for c, _ in interface.STATUSES] == re.findall(r"^\s+(SQ_\w+),", text, re.MULTILINE)
    assert [c for c, _, _ in interface.STATS] == re.findall(r"^\s+(ST_\w+),", text, re.MULTILINE)
    assert STATUSES == tuple(name for _, name in interface.STATUSES)
    assert STATS == tuple(name for _, name, _ in interface.STATS)
    # sqp.h (what the export writes) carries the generated text
    assert text.strip() in c_source("sqp.h")


def test_the_compiled_library_reports_the_tables_sizes() -> None:
    system = load_config("paper").make_problem().system
    lib = sqp_library(system, 0.2)  # (_declare refuses a library of other tables)
    assert lib.lfm_sqp_options_size() == ctypes.sizeof(interface.SqpOptions)
    assert lib.lfm_sqp_status_count() == len(STATUSES)
    assert lib.lfm_sqp_stats_count() == len(STATS)


def test_no_c_file_keeps_a_copy_of_an_index_or_a_status_name() -> None:
    folders = [
        resources.files("controllers.solvers.fast.codegen") / "c",
        resources.files("controllers.export") / "c",
    ]
    for folder in folders:
        for item in folder.iterdir():
            if not item.name.endswith((".c", ".h")):
                continue
            text = item.read_text(encoding="utf-8")
            # the statistics are read by their ST_ names, never by a number
            assert not re.search(r"stats\[\d+\]", text), item.name
            assert not re.search(r"enum\s*\{\s*SQ_SUCCEEDED", text), item.name
            # nor a table of the status names (two in a row)
            names = [name for _, name in interface.STATUSES]
            for a, b in zip(names, names[1:], strict=False):
                assert not re.search(f'"{a}",\\s*"{b}"', text), (item.name, a)
