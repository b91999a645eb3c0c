"""The C code the fast solver generates from a system: CasADi's point functions rewritten for
vectorised loops (:mod:`.inline`), the fixed C driver around them (the C files of ``c/``:
``driver.c``, which includes ``selection.c``, ``hessian.c`` and ``clones.h``; beside them
``elastic_ipm.c``, the QP solver of :mod:`controllers.solvers.fast.qp.elastic_ipm`), the
whole C source of a system's library (:mod:`.source`), and the build and cache of the shared
library (:mod:`.build`, with the cache's trust checks in :mod:`.trust`)."""
