"""The C code the fast solver generates from a system: CasADi's point functions rewritten for
vectorised loops (:mod:`.inline`), the fixed C driver around them, and the build and cache of
the shared library (:mod:`.build`)."""
