"""The system's generated point functions as inline C the C library's scenario loops vectorise.

CasADi writes a function as C that reads its inputs through ``const casadi_real** arg`` and
writes through ``casadi_real** res`` (each checked for NULL). Called once per scenario, it
keeps the compiler from vectorising the loop over the scenarios: it cannot see through the
pointer arrays. The functions here rewrite the generated body of a point function (straight-
line code of an SX function: scalar temporaries, arithmetic and math calls) into a ``static
inline`` function of plain strided pointers, which the driver (``codegen/c/driver.c``) calls
inside ``#pragma omp simd`` loops over the scenarios of one step: the rollout's step
(:func:`inline_step`), the Hessian's recursion step (:func:`inline_step_curv`) and the
linearisation's step and constraint Jacobians (:func:`inline_step_jac`,
:func:`inline_con_jac`). Each defines a macro (``LFM_STEP_INLINE``,
...) that switches the driver to its vectorisable path; a body the rewrite does not handle
raises :class:`NotInlinable` and the driver keeps one call per scenario there.

The math functions glibc's vector math library (libmvec) has had since 2.22 (``sin``,
``cos``, ``exp``, ``log``, ``pow``) are renamed ``lfm_v*``: with ``LFM_VECTOR_MATH`` defined
(the C library is built with ``-lmvec``) these are declared as the same C functions under the
same symbols, with GCC's ``simd`` attribute, so the vectorised loops call libmvec's variants
(``_ZGVbN2v_sin`` and so on); else they are the plain functions. (Under their own names the
compiler would also merge ``sin(a)`` and ``cos(a)`` into one scalar ``sincos``, which has no
such variant and stops the vectorisation.)
"""

from __future__ import annotations

import re

import casadi as ca

# glibc's libmvec functions (x86_64, since 2.22) that the inlined body calls by vector name.
VECTOR_MATH = ("sin", "cos", "exp", "log", "pow")

VECTOR_MATH_DECLARATIONS = "\n".join(
    [
        "#if defined(LFM_VECTOR_MATH) && defined(__GNUC__) && !defined(__clang__)",
        "#define LFM_VECTOR_MATH_USED 1",
        '#define LFM_VECTOR_FN __attribute__((const, __simd__("notinbranch")))',
        *(
            f"extern double lfm_v{name}({'double, double' if name == 'pow' else 'double'})"
            f' __asm__("{name}") LFM_VECTOR_FN;'
            for name in VECTOR_MATH
        ),
        "#else",
        *(f"#define lfm_v{name} {name}" for name in VECTOR_MATH),
        "#endif",
    ]
)

_ARG = re.compile(r"arg\[(\d+)\]\s*\?\s*arg\[\1\]\[(\d+)\]\s*:\s*0")
_RES = re.compile(r"if \(res\[0\]!=0\) res\[0\]\[(\d+)\]=")
_MATH = re.compile(r"\b(" + "|".join(VECTOR_MATH) + r")\(")


class NotInlinable(ValueError):
    """The generated body uses something the inline rewrite does not handle."""


def function_body(source: str, name: str) -> str:
    """The statements of the generated function that the exported ``name`` calls."""
    wrapper = re.search(
        rf"int {re.escape(name)}\(const casadi_real\*\* arg[^{{]*\{{\s*return (casadi_f\d+)\(",
        source,
    )
    if wrapper is None:
        raise NotInlinable(f"no exported function {name!r} in the generated code")
    inner = wrapper.group(1)
    start = source.find(f"static int {inner}(")
    if start < 0:
        raise NotInlinable(f"no body of {inner} ({name})")
    open_ = source.index("{", start)
    end = source.index("\n}\n", open_)
    body = re.sub(r"\n\s*return 0;\s*$", "", source[open_ + 1 : end])
    return body.strip("\n") + "\n"


# The point functions' inputs (x, u, w, p) on strided pointers: x by the state stride xs,
# w by the force component stride ws.
_POINT_READS = {0: "x_[{}*xs]", 1: "u_[{}]", 2: "w_[{}*ws]", 3: "p_[{}]"}
_POINT_PARAMS = (
    "const casadi_real* x_, long xs, const casadi_real* u_, const casadi_real* w_,\n"
    "    long ws, const casadi_real* p_"
)


def _inline(source: str, fn: ca.Function, name: str, reads: dict, params: str, write) -> str:
    """``static inline void name(params)``: the generated body of ``fn`` with its input
    ``i``'s ``j``-th value read as ``reads[i].format(j)`` and its ``j``-th output value
    written as ``write(j)``; and ``#define`` of ``name`` in capitals (the driver's switch).

    Raises:
        NotInlinable: ``fn`` has other inputs than ``reads`` or more than one output, or its
            body reads or writes other than element by element (work arrays, calls of other
            generated functions).
    """
    if fn.n_in() != len(reads) or fn.n_out() != 1:
        raise NotInlinable(f"{fn.name()}: expected {len(reads)} inputs and 1 output")
    body = function_body(source, fn.name())
    body = _ARG.sub(lambda m: reads[int(m.group(1))].format(m.group(2)), body)
    body = _RES.sub(lambda m: write(int(m.group(1))), body)
    body = _MATH.sub(lambda m: f"lfm_v{m.group(1)}(", body)
    leftover = re.search(r"\b(arg|res|iw|w)\[|casadi_f\d+\(", body)
    if leftover:
        raise NotInlinable(f"{fn.name()}: cannot rewrite {leftover.group(0)!r}")
    unused = " ".join(f"(void){p.split()[-1].lstrip('*')};" for p in params.split(","))
    return (
        f"#define {name.upper()} 1\n"
        f"static inline __attribute__((always_inline)) void {name}(\n"
        f"    {params}) {{\n  {unused}\n" + body + "}\n"
    )


def inline_step(source: str, fn: ca.Function, nx: int) -> str:
    """``lfm_step_inline``: the body of ``fn`` (``lfm_step(x, u, w, p) -> [F; g(F)]``, as
    generated in ``source``) on strided pointers.

    Its arguments: ``x_`` (stride ``xs``), ``u_``, ``w_`` (stride ``ws``), ``p_``; the
    outputs ``F`` to ``xo_`` (stride ``xs``) and ``g(F)`` to ``go_`` (stride ``gs``).

    Raises:
        NotInlinable: as :func:`_inline` (four inputs).
    """

    def write(j: int) -> str:
        return f"xo_[{j}*xs]=" if j < nx else f"go_[{j - nx}*gs]="

    params = _POINT_PARAMS + ", casadi_real* xo_, casadi_real* go_, long gs"
    return _inline(source, fn, "lfm_step_inline", _POINT_READS, params, write)


def inline_step_curv(source: str, fn: ca.Function) -> str:
    """``lfm_step_curv_inline``: the body of ``fn`` (``lfm_step_curv(x, u, w, p, lam, v)``,
    one step of the Hessian's backward recursion) on strided pointers: ``x_``, ``u_``,
    ``w_``, ``p_`` as in :func:`inline_step`, ``l_`` and ``v_`` (``lam`` and ``v``) by the
    block stride ``bs``, its ``j``-th value written to ``o_[j * bs]``.

    Raises:
        NotInlinable: as :func:`_inline` (six inputs).
    """
    reads = {**_POINT_READS, 4: "l_[{}*bs]", 5: "v_[{}*bs]"}
    params = (
        _POINT_PARAMS
        + ",\n    const casadi_real* l_, const casadi_real* v_, long bs, casadi_real* o_"
    )
    return _inline(source, fn, "lfm_step_curv_inline", reads, params, _block_write)


def inline_step_jac(source: str, fn: ca.Function) -> str:
    """``lfm_step_jac_inline``: the body of ``fn`` (``lfm_step_jac(x, u, w, p)``: ``A`` then
    ``B``, row-major) with the inputs of :func:`inline_step` and its ``j``-th value written
    to ``o_[j * bs]``.

    Raises:
        NotInlinable: as :func:`_inline` (four inputs).
    """
    params = _POINT_PARAMS + ", long bs, casadi_real* o_"
    return _inline(source, fn, "lfm_step_jac_inline", _POINT_READS, params, _block_write)


def inline_con_jac(source: str, fn: ca.Function) -> str:
    """``lfm_con_jac_inline``: the body of ``fn`` (``lfm_con_jac(x)``, the constraints'
    Jacobian ``(ng, nx)`` row-major) with ``x`` read as ``x_[j * xs]`` and its ``j``-th value
    written to ``o_[j * bs]``.

    Raises:
        NotInlinable: as :func:`_inline` (one input).
    """
    params = "const casadi_real* x_, long xs, long bs, casadi_real* o_"
    return _inline(source, fn, "lfm_con_jac_inline", {0: "x_[{}*xs]"}, params, _block_write)


def _block_write(j: int) -> str:
    """The ``j``-th output value into a block of scenarios (stride ``bs``)."""
    return f"o_[{j}*bs]="


__all__ = [
    "NotInlinable",
    "VECTOR_MATH",
    "VECTOR_MATH_DECLARATIONS",
    "function_body",
    "inline_con_jac",
    "inline_step",
    "inline_step_curv",
    "inline_step_jac",
]
