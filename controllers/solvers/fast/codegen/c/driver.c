#include <stdlib.h>
#include <string.h>
#include <math.h>
#define NZ (NX + NU)
/* Threads: the scenarios are cut into T contiguous chunks, one per thread (OpenMP when the
   library is compiled with it, else the chunks one after another). Chunk 0 accumulates its
   sums into the outputs, the others into their own arrays, added in chunk order: the
   results depend on T (rounding), not on the run, and T = 1 is the serial sweep itself. */
#define CHUNK(ns, t, T) ((ns) * (t) / (T))
static long chunks(long nthreads, long ns) {
  long T = nthreads < 1 ? 1 : nthreads;
  return ns < T ? (ns > 0 ? ns : 1) : T;
}
CASADI_SYMBOL_EXPORT int lfm_vector_math(void) {
  /* 2: loops over scenarios call the generated point functions inlined (vectorisable) and
     with libmvec's vector math, 1: inlined, 0: one call of a generated function per scenario
     everywhere (which are inlined: LFM_STEP_INLINE, LFM_STEP_CURV_INLINE,
     LFM_STEP_JAC_INLINE, LFM_CON_JAC_INLINE). */
#if defined(LFM_STEP_INLINE) || defined(LFM_STEP_CURV_INLINE) || defined(LFM_STEP_JAC_INLINE)
#define LFM_ANY_INLINE 1
#endif
#if defined(LFM_ANY_INLINE) && defined(LFM_VECTOR_MATH_USED)
  return 2;
#elif defined(LFM_ANY_INLINE)
  return 1;
#else
  return 0;
#endif
}
CASADI_SYMBOL_EXPORT int lfm_openmp(void) {
#ifdef _OPENMP
  return 1;
#else
  return 0;
#endif
}
/* S at step k from 0 (the sensitivities of x_{k+1}, and with feedback of u_{s,k} below them:
   NXS rows per scenario). */
#define S_OFF(k, ns) ((ns) * NXS * NU * (k) * ((k) + 1) / 2)

#include "clones.h"

typedef int (*cfun)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int);
typedef struct {
  const casadi_real** arg; casadi_real** res; casadi_int* iw; casadi_real* w;
} work_t;

static int work_alloc(work_t* wk) {
  casadi_int a = 0, r = 0, i = 0, w = 0, sa, sr, si, sw;
#define W(f) f##_work(&sa, &sr, &si, &sw); a = a > sa ? a : sa; r = r > sr ? r : sr; \
  i = i > si ? i : si; w = w > sw ? w : sw;
  @WORK@
#undef W
  wk->arg = malloc((a + 1) * sizeof(void*));
  wk->res = malloc((r + 1) * sizeof(void*));
  wk->iw = malloc((i + 1) * sizeof(casadi_int));
  wk->w = malloc((w + 1) * sizeof(casadi_real));
  return wk->arg && wk->res && wk->iw && wk->w ? 0 : 1;
}

static void work_free(work_t* wk) { free(wk->arg); free(wk->res); free(wk->iw); free(wk->w); }

#define CALL1(f, a0, r0) (wk.arg[0] = (a0), wk.res[0] = (r0), f(wk.arg, wk.res, wk.iw, wk.w, 0))
#define CALL2(f, a0, a1, r0) (wk.arg[1] = (a1), CALL1(f, a0, r0))
#define CALL3(f, a0, a1, a2, r0) (wk.arg[2] = (a2), CALL2(f, a0, a1, r0))
#define CALL4(f, a0, a1, a2, a3, r0) (wk.arg[3] = (a3), CALL3(f, a0, a1, a2, r0))
#define CALL5(f, a0, a1, a2, a3, a4, r0) (wk.arg[4] = (a4), CALL4(f, a0, a1, a2, a3, r0))
#define CALL6(f, a0, a1, a2, a3, a4, a5, r0) (wk.arg[5] = (a5), CALL5(f, a0, a1, a2, a3, a4, r0))

/* The input-only parts p of a step function for every step k: P (N, np); NULL on failure. */
static double* parametric(work_t* wk, cfun f, long np, long n, const double* u) {
  double* P = malloc((n * np + 1) * sizeof(double));
  if (!P) return NULL;
  for (long k = 0; k < n; ++k) {
    wk->arg[0] = u + k * ND;
    wk->res[0] = P + k * np;
    if (f(wk->arg, wk->res, wk->iw, wk->w, 0)) { free(P); return NULL; }
  }
  return P;
}

/* 1 if every Wq_k (N of them) is diagonal: weighted() then skips the zeros (same result). */
static int diagonal(const double* Wq, long n) {
  for (long a = 0; a < n * NX * NX; ++a)
    if ((a % (NX * NX)) % (NX + 1) && Wq[a] != 0.0) return 0;
  return 1;
}

/* Weighted state error of the state x[m xs] (m < NX): out = scale Wk (x - goal); returns
   (x - goal)' Wk (x - goal). diag: Wk is diagonal (diagonal()). Always inlined: with diag
   and out constants at a call, the branches on them fold away (the vectorised rollout). */
static inline __attribute__((always_inline)) double weighted_at(const double* x, long xs,
    const double* goal, const double* Wk, int diag, double scale, double* out) {
  double e[NX], c = 0.0;
  for (int m = 0; m < NX; ++m) e[m] = x[m * xs] - goal[m];
  for (int m = 0; m < NX; ++m) {
    double s = 0.0;
    if (diag)
      s = Wk[m * NX + m] * e[m];
    else
      for (int r = 0; r < NX; ++r) s += Wk[m * NX + r] * e[r];
    if (out) out[m] = scale * s;
    c += e[m] * s;
  }
  return c;
}

/* weighted_at of a contiguous state. */
static inline __attribute__((always_inline)) double weighted(const double* x,
    const double* goal, const double* Wk, int diag, double scale, double* out) {
  return weighted_at(x, 1, goal, Wk, diag, scale, out);
}

/* The force of step k, scenario i: W[a sa + k sk + i si] (strides in elements). */
static const double* gather(const double* W, long sa, long sk, long si, long k, long i,
                            double* wv) {
  for (int a = 0; a < NW; ++a) wv[a] = W[a * sa + k * sk + i * si];
  return wv;
}

static void load_state(const double* X, long k, long ns, long i, double* x) {
  for (int m = 0; m < NX; ++m) x[m] = X[(k * NX + m) * ns + i];
}

/* Sum of a[p] b[p], p < len, in four interleaved partial sums. */
static double dot(const double* a, const double* b, long len) {
  double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
  long p = 0;
  for (; p + 4 <= len; p += 4) {
    s0 += a[p] * b[p];
    s1 += a[p + 1] * b[p + 1];
    s2 += a[p + 2] * b[p + 2];
    s3 += a[p + 3] * b[p + 3];
  }
  for (; p < len; ++p) s0 += a[p] * b[p];
  return (s0 + s1) + (s2 + s3);
}

#ifdef LFM_FEEDBACK
/* Feedback problems (the library of a feedback prediction: LFM_FEEDBACK). The data row of
   step k (the "u" of the generated functions, ND values) is [v_k (NU), K_k (NU, NX) row-major,
   r_k (NX), R (NU, NU) row-major, active]: the nominal input, the law, the input weight and
   whether the step's input rows count (0 where they are redundant with v_k's hard bounds,
   K_k = 0). A scenario applies u = v_k + K_k (x - r_k). */
#define D_K NU
#define D_R (NU + NU * NX)
#define D_RW NDF
#define D_ACTIVE (NDF + NU * NU)

/* The input u (NU) of the state x[m xs] under the data row d. */
static inline __attribute__((always_inline)) void fb_applied(const double* x, long xs,
                                                             const double* d, double* u) {
  for (int q = 0; q < NU; ++q) {
    double s = d[q];
    for (int m = 0; m < NX; ++m) s += d[D_K + q * NX + m] * (x[m * xs] - d[D_R + m]);
    u[q] = s;
  }
}

/* A scenario's input at the state x[m xs]: its rows u - hi at g[(NG + q) gs] and lo - u at
   g[(NG + NU + q) gs] (-inf where the step's rows do not count), u into uo; returns u' R u. */
static inline __attribute__((always_inline)) double fb_input(const double* x, long xs,
    const double* d, double* g, long gs, double* uo) {
  const int active = d[D_ACTIVE] != 0.0;
  double c = 0.0;
  fb_applied(x, xs, d, uo);
  for (int q = 0; q < NU; ++q) {
    g[(NG + q) * gs] = active ? uo[q] - U_HI[q] : -INFINITY;
    g[(NG + NU + q) * gs] = active ? U_LO[q] - uo[q] : -INFINITY;
    double t = 0.0;
    for (int p = 0; p < NU; ++p) t += d[D_RW + q * NU + p] * uo[p];
    c += uo[q] * t;
  }
  return c;
}
#endif

#ifdef LFM_STEP_INLINE
/* Scenarios i0 <= i < i1 of lfm_rollout; their state cost into *cost. Step by step, each
   step's scenarios in one vectorisable loop over the step's inlined body (lfm_step_inline);
   each scenario's cost summed over the steps, then the scenarios' sums in order. */
LFM_CLONES static int rollout_chunk(work_t* wkp, long n, long ns, long i0, long i1,
    const double* x0T, const double* W, long sa, long sk, long si, const double* u, const double* P,
    const double* goal, const double* Wq, int diag, double* X, double* G, double* cost) {
  (void)wkp;
  double* ci = calloc(i1 - i0 + 1, sizeof(double));
  if (!ci) return 1;
  for (int m = 0; m < NX; ++m)
    memcpy(X + m * ns + i0, x0T + m * ns + i0, (i1 - i0) * sizeof(double));
  for (long k = 0; k < n; ++k) {
    const double* xk = X + k * NX * ns;
    double* xn = X + (k + 1) * NX * ns;
    double* gk = G + k * ns; /* (G is unused without constraints) */
    const double* uk = u + k * ND;
    const double* pk = P + k * NP_STEP;
    const double* Wk = Wq + k * NX * NX;
    const double* wk = W + k * sk;
    /* (two loops, each with diag a constant: a branch on it inside would stop the
       vectorisation) */
    if (diag) {
#pragma omp simd
      for (long i = i0; i < i1; ++i) {
        lfm_step_inline(xk + i, ns, uk, wk + i * si, sa, pk, xn + i, gk + i, n * ns);
        ci[i - i0] += weighted_at(xn + i, ns, goal, Wk, 1, 1.0, NULL);
#ifdef LFM_FEEDBACK
        double ui[NU];
        ci[i - i0] += fb_input(xk + i, ns, uk, gk + i, n * ns, ui);
#endif
      }
    } else {
#pragma omp simd
      for (long i = i0; i < i1; ++i) {
        lfm_step_inline(xk + i, ns, uk, wk + i * si, sa, pk, xn + i, gk + i, n * ns);
        ci[i - i0] += weighted_at(xn + i, ns, goal, Wk, 0, 1.0, NULL);
#ifdef LFM_FEEDBACK
        double ui[NU];
        ci[i - i0] += fb_input(xk + i, ns, uk, gk + i, n * ns, ui);
#endif
      }
    }
  }
  double c = 0.0;
  for (long i = 0; i < i1 - i0; ++i) c += ci[i];
  free(ci);
  *cost = c;
  return 0;
}
#else
/* Scenarios i0 <= i < i1 of lfm_rollout; their state cost into *cost. */
static int rollout_chunk(work_t* wkp, long n, long ns, long i0, long i1, const double* x0T,
    const double* W, long sa, long sk, long si, const double* u, const double* P,
    const double* goal, const double* Wq, int diag, double* X, double* G, double* cost) {
  work_t wk = *wkp;
  double x[NX], xn[NX + NG], wv[NW + 1], c = 0.0; /* xn: the next state, its constraints */
  int status = 0;
  for (long i = i0; i < i1 && !status; ++i) {
    for (int m = 0; m < NX; ++m) X[m * ns + i] = x[m] = x0T[m * ns + i];
    for (long k = 0; k < n && !status; ++k) {
      gather(W, sa, sk, si, k, i, wv);
      status = CALL4(lfm_step, x, u + k * ND, wv, P + k * NP_STEP, xn);
#ifdef LFM_FEEDBACK
      double ui[NU];
      c += fb_input(x, 1, u + k * ND, G + k * ns + i, n * ns, ui);
#endif
      for (int m = 0; m < NX; ++m) X[((k + 1) * NX + m) * ns + i] = x[m] = xn[m];
      c += weighted(x, goal, Wq + k * NX * NX, diag, 1.0, NULL);
#if NG > 0
      for (int j = 0; j < NG; ++j) G[(j * n + k) * ns + i] = xn[NX + j];
#else
      (void)G;
#endif
    }
  }
  *cost = c;
  return status;
}
#endif

CASADI_SYMBOL_EXPORT int lfm_rollout(long n, long ns, const double* x0T, const double* W,
    long sa, long sk, long si, const double* u, const double* goal, const double* Wq,
    double* X, double* G, double* cost, long nthreads) {
  /* The states X (N+1, NX, Ns), constraint values G (NG, N, Ns) of every scenario and the
     state cost summed over them, sum_i sum_k (x_k - goal)' Wq_k (x_k - goal). With feedback
     (LFM_FEEDBACK): u is the data rows (N, ND); G (NGR, N, Ns) holds the input rows of
     each step's input after the state constraints, and the cost each scenario's u' R u. */
  work_t wk;
  if (work_alloc(&wk)) return 1;
  double* P = parametric(&wk, lfm_step_pre, NP_STEP, n, u);
  if (!P) { work_free(&wk); return 1; }
  const long T = chunks(nthreads, ns);
  const int diag = diagonal(Wq, n);
  int status = 0;
  if (T == 1) {
    status = rollout_chunk(&wk, n, ns, 0, ns, x0T, W, sa, sk, si, u, P, goal, Wq, diag, X, G,
                           cost);
  } else {
    double* part = malloc(T * sizeof(double));
    int* st = malloc(T * sizeof(int));
    if (!part || !st) { free(part); free(st); free(P); work_free(&wk); return 1; }
#pragma omp parallel for num_threads(T) schedule(static, 1)
    for (long t = 0; t < T; ++t) {
      work_t own;
      st[t] = work_alloc(&own) ? 1
          : rollout_chunk(&own, n, ns, CHUNK(ns, t, T), CHUNK(ns, t + 1, T), x0T, W, sa, sk,
                          si, u, P, goal, Wq, diag, X, G, part + t);
      work_free(&own);
    }
    double c = 0.0;
    for (long t = 0; t < T; ++t) { c += part[t]; status |= st[t]; }
    *cost = c;
    free(part);
    free(st);
  }
  free(P);
  work_free(&wk);
  return status;
}

#ifdef LFM_STEP_JAC_INLINE
#define JAC_BLOCK 32 /* scenarios whose Jacobians are evaluated together */
/* The step Jacobians (into Jb) and, with constraints, the constraint Jacobians at the next
   states (into Cb) of nb (<= JAC_BLOCK) scenarios of one step, each in one vectorisable loop
   (entry e of scenario b at e JAC_BLOCK + b). On its own, so that only these loops have the
   x86-64-v3 version (LFM_CLONES). */
LFM_CLONES static void jac_block(long nb, const double* x, long ns, const double* u,
    const double* w, long sa, long si, const double* p, double* Jb, double* Cb) {
#pragma omp simd
  for (long b = 0; b < nb; ++b)
    lfm_step_jac_inline(x + b, ns, u, w + b * si, sa, p, JAC_BLOCK, Jb + b);
#if NG > 0 && defined(LFM_CON_JAC_INLINE)
#pragma omp simd
  for (long b = 0; b < nb; ++b) lfm_con_jac_inline(x + NX * ns + b, ns, JAC_BLOCK, Cb + b);
#else
  (void)Cb;
#endif
}
#endif

/* Scenarios i0 <= i < i1 of lfm_linearise; their gradient terms added into grad. With the
   Jacobians inlined (LFM_STEP_JAC_INLINE), a step's scenarios in blocks: their Jacobians
   first (jac_block), then each one's products. */
static int linearise_chunk(work_t* wkp, long n, long ns, long i0, long i1, const double* X,
    const double* W, long sa, long sk, long si, const double* u, const double* P,
    const double* goal, const double* Wq, int diag, double scale, double* S, double* Jg,
    double* grad) {
  work_t wk = *wkp;
  double x[NX], gx[NX], wv[NW + 1];
  /* The step Jacobian of scenario i: A_k (NX, NX) then B_k (NX, NU), row-major, entry e at
     Jp[e js] (from lfm_step_jac's call, or a column of the block's values) */
#ifdef LFM_STEP_JAC_INLINE
  double Jb[NX * NZ * JAC_BLOCK], Cb[NG * NX * JAC_BLOCK + 1];
  const long js = JAC_BLOCK;
  (void)wv;
#else
  double J[NX * NZ];
  const double* Jp = J;
  const long js = 1;
#endif
  int status = 0;
  for (long k = 0; k < n && !status; ++k) {
    for (long i = i0; i < i1 && !status; ++i) {
#ifdef LFM_STEP_JAC_INLINE
      const long b = (i - i0) % JAC_BLOCK;
      if (b == 0)
        jac_block(i1 - i < JAC_BLOCK ? i1 - i : JAC_BLOCK, X + k * NX * ns + i, ns, u + k * ND,
                  W + k * sk + i * si, sa, si, P + k * NP_STEP_JAC, Jb, Cb);
      const double* Jp = Jb + b;
#else
      load_state(X, k, ns, i, x);
      gather(W, sa, sk, si, k, i, wv);
      status = CALL4(lfm_step_jac, x, u + k * ND, wv, P + k * NP_STEP_JAC, J);
#endif
      const long cols = k * NU, width = cols + NU; /* S_{k+1} = [A_k S_k, B_k] */
      double* Sk = S + S_OFF(k, ns) + i * NXS * width;
      const double* Sp = k ? S + S_OFF(k - 1, ns) + i * NXS * cols : NULL;
      for (int r = 0; r < NX; ++r) {
        double* row = Sk + r * width;
        double a[NX];
        for (int m = 0; m < NX; ++m) a[m] = Jp[(r * NX + m) * js];
        for (long c = 0; c < cols; ++c) {
          double s = 0.0;
          for (int m = 0; m < NX; ++m)
            if (A_NZ[r * NX + m]) s += a[m] * Sp[m * cols + c];
          row[c] = s;
        }
        for (int q = 0; q < NU; ++q) row[cols + q] = Jp[(NX * NX + r * NU + q) * js];
      }
#ifdef LFM_FEEDBACK
      /* the input's sensitivities below x_{k+1}'s: du/dv = K_k S_k + [0, I] */
      const double* dk = u + k * ND;
      double gu[NU]; /* scale R u: the input cost's gradient */
      {
        double uk[NU];
        load_state(X, k, ns, i, x);
        fb_applied(x, 1, dk, uk);
        for (int q = 0; q < NU; ++q) {
          double t = 0.0;
          for (int p = 0; p < NU; ++p) t += dk[D_RW + q * NU + p] * uk[p];
          gu[q] = scale * t;
          double* row = Sk + (NX + q) * width;
          for (long c = 0; c < cols; ++c) {
            double t2 = 0.0;
            for (int m = 0; m < NX; ++m) t2 += dk[D_K + q * NX + m] * Sp[m * cols + c];
            row[c] = t2;
          }
          for (int p = 0; p < NU; ++p) row[cols + p] = p == q ? 1.0 : 0.0;
        }
      }
#endif
      load_state(X, k + 1, ns, i, x);
#if NGR > 0
      double* Jgi = Jg + (k * ns + i) * GR_NNZ; /* its entries that can be nonzero */
#endif
#ifdef LFM_FEEDBACK
      for (int q = 0; q < NU; ++q) Jgi[G_NNZ + q] = 1.0, Jgi[G_NNZ + NU + q] = -1.0;
#endif
#if NG > 0
#if defined(LFM_STEP_JAC_INLINE) && defined(LFM_CON_JAC_INLINE)
      for (int e = 0; e < G_NNZ; ++e) Jgi[e] = Cb[G_IDX[e] * JAC_BLOCK + b];
#else
      double Jd[NG * NX]; /* (NG, NX) row-major */
      status |= CALL1(lfm_con_jac, x, Jd);
      for (int e = 0; e < G_NNZ; ++e) Jgi[e] = Jd[G_IDX[e]];
#endif
#else
      (void)Jg;
#endif
      weighted(x, goal, Wq + k * NX * NX, diag, scale, gx);
      /* (each entry of grad once per scenario: its updates are one long chain through
         memory, and NX updates per entry made that chain the call's bottleneck) */
      for (long c = 0; c < width; ++c) {
        double t = 0.0;
        for (int r = 0; r < NX; ++r) t += gx[r] * Sk[r * width + c];
#ifdef LFM_FEEDBACK
        for (int q = 0; q < NU; ++q) t += gu[q] * Sk[(NX + q) * width + c];
#endif
        grad[c] += t;
      }
    }
  }
  (void)wk;
  return status;
}

CASADI_SYMBOL_EXPORT int lfm_linearise(long n, long ns, const double* X, const double* W,
    long sa, long sk, long si, const double* u, const double* goal, const double* Wq,
    double scale, double* S, double* Jg, double* grad, long nthreads) {
  /* S, Jg and the state part of the gradient, sum_k sum_i S_k' scale Wq_k (x_k - goal) (the
     step Jacobians A_k are used where they are computed and not stored).
     Step by step, all scenarios (of a chunk) at each: S_{k+1} is written, and S_k read, in
     the arrays' (step, scenario) order (a scenario-by-scenario sweep wrote N blocks at N
     distant places per scenario, and took 1.6x as long at Ns = 5000). */
  work_t wk;
  if (work_alloc(&wk)) return 1;
  double* P = parametric(&wk, lfm_step_jac_pre, NP_STEP_JAC, n, u);
  if (!P) { work_free(&wk); return 1; }
  const long nut = n * NU, T = chunks(nthreads, ns);
  const int diag = diagonal(Wq, n);
  int status = 0;
  memset(grad, 0, nut * sizeof(double));
  if (T == 1) {
    status = linearise_chunk(&wk, n, ns, 0, ns, X, W, sa, sk, si, u, P, goal, Wq, diag, scale, S,
                             Jg, grad);
  } else {
    double* part = calloc((T - 1) * nut + 1, sizeof(double)); /* chunks 1.. */
    int* st = malloc(T * sizeof(int));
    if (!part || !st) { free(part); free(st); free(P); work_free(&wk); return 1; }
#pragma omp parallel for num_threads(T) schedule(static, 1)
    for (long t = 0; t < T; ++t) {
      work_t own;
      st[t] = work_alloc(&own) ? 1
          : linearise_chunk(&own, n, ns, CHUNK(ns, t, T), CHUNK(ns, t + 1, T), X, W, sa, sk,
                            si, u, P, goal, Wq, diag, scale, S, Jg,
                            t ? part + (t - 1) * nut : grad);
      work_free(&own);
    }
    for (long t = 0; t < T; ++t) status |= st[t];
    for (long t = 1; t < T; ++t)
      for (long c = 0; c < nut; ++c) grad[c] += part[(t - 1) * nut + c];
    free(part);
    free(st);
  }
  free(P);
  work_free(&wk);
  return status;
}

/* S_k d of scenario i (step k from 0; causal: over the first (k + 1) NU inputs) into sd. */
static inline void step_change(const double* S, long k, long ns, long i, const double* d,
                               double* sd) {
  const long width = (k + 1) * NU;
  const double* Sk = S + S_OFF(k, ns) + i * NXS * width;
  for (int m = 0; m < NXS; ++m) sd[m] = dot(Sk + m * width, d, width);
}

/* G + Jg_k[j] sd: the value of constraint j at step k of scenario i, changed to first
   order by the state change sd. */
static inline double linear_value(long n, long ns, const double* Jg, const double* G, long j,
                                  long k, long i, const double* sd) {
  const double* jg = Jg + (k * ns + i) * GR_NNZ;
  double s = 0.0;
  for (int e = GR_PTR[j]; e < GR_PTR[j + 1]; ++e) s += jg[e] * sd[GR_COL[e]];
  return G[(j * n + k) * ns + i] + s;
}

CASADI_SYMBOL_EXPORT int lfm_linear_change(long n, long ns, const double* S,
    const double* Jg, const double* G, const double* d, double* out) {
  /* out (NG, N, Ns) = G + Jg_k S_k d: every constraint value changed to first order along
     the input step d, in G's layout. */
  for (long k = 0; k < n; ++k)
    for (long i = 0; i < ns; ++i) {
      double sd[NXS];
      step_change(S, k, ns, i, d, sd);
      for (int j = 0; j < NGR; ++j)
        out[(j * n + k) * ns + i] = linear_value(n, ns, Jg, G, j, k, i, sd);
    }
  return 0;
}

CASADI_SYMBOL_EXPORT int lfm_rows(long n, long ns, const double* S, const double* Jg,
    long r, const long* pos, double* out) {
  /* out (r, N NU): the Jacobian rows Jg_k[j] S_k of the scenario rows pos (r, 3) of
     (constraint j, step k from 0, scenario i); zero beyond the first (k + 1) NU columns. */
  const long nut = n * NU;
  for (long q = 0; q < r; ++q) {
    const long j = pos[3 * q], k = pos[3 * q + 1], i = pos[3 * q + 2], width = (k + 1) * NU;
    const double* Sk = S + S_OFF(k, ns) + i * NXS * width;
    const double* jg = Jg + (k * ns + i) * GR_NNZ;
    double* row = out + q * nut;
    for (long c = 0; c < width; ++c) {
      double s = 0.0;
      for (int e = GR_PTR[j]; e < GR_PTR[j + 1]; ++e) s += jg[e] * Sk[GR_COL[e] * width + c];
      row[c] = s;
    }
    for (long c = width; c < nut; ++c) row[c] = 0.0;
  }
  return 0;
}

#include "selection.c"

#include "hessian.c"
