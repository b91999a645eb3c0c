/* Two versions of the vectorised loops where GCC (>= 11) and glibc (IFUNC) can dispatch at
   load time: one for x86-64-v3 (AVX2 and FMA: four scenarios per instruction, libmvec's AVX2
   functions) and the baseline; the running CPU picks (so a cached kernel stays portable).
   Compiled with -DLFM_NO_CLONES: the baseline only (the tests check it on AVX2 machines). */
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && defined(__x86_64__) \
    && defined(__GLIBC__) && !defined(LFM_NO_CLONES)
#define LFM_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define LFM_CLONES
#endif
