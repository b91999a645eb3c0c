/* Small dense linear algebra of the compiled SQP loop (sqp.c): a Cholesky test, a symmetric
   eigen-decomposition (cyclic Jacobi) and a dual active-set QP solver for the QPs without
   slacks (Goldfarb and Idnani's method). Written for the fast SQP's sizes: n = N nu inputs
   (14 at N = 7, 60 at N = 30), matrices row-major. Names start with dq_ (static) or
   lfm_dense_ (exported, for the tests). */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "clones.h"

/* The eigen-decomposition and the QP solver in the clones of clones.h, without contracting
   a product and a sum into one fused multiply-add: every clone rounds as the baseline (their
   loops vectorise only element by element; no sum is reordered). */
#if defined(__GNUC__) && !defined(__clang__)
#define DQ_CLONES LFM_CLONES __attribute__((optimize("fp-contract=off")))
#define DQ_INLINE static inline __attribute__((always_inline, optimize("fp-contract=off")))
#else
#define DQ_CLONES LFM_CLONES
#define DQ_INLINE static inline
#endif

/* 1 if the symmetric M (n, n) has a Cholesky factor (every pivot > 0, as LAPACK's dpotrf on
   its lower triangle decides), else 0. M is read only; work: n * n doubles. */
/* Column j of the Cholesky factor below the diagonal (l = L[j, j]): L[i, j] = (M[i, j] -
   sum_k<j L[i, k] L[j, k]) / l for i > j, four rows' sums side by side (each in k order). */
DQ_INLINE void dq_cholesky_column(long n, long j, double l, const double* M, double* L) {
  const double* Lj = L + j * n;
  long i = j + 1;
  for (; i + 4 <= n; i += 4) {
    double *L0 = L + i * n, *L1 = L0 + n, *L2 = L1 + n, *L3 = L2 + n;
    double t0 = M[i * n + j], t1 = M[(i + 1) * n + j], t2 = M[(i + 2) * n + j];
    double t3 = M[(i + 3) * n + j];
    for (long k = 0; k < j; ++k) {
      const double c = Lj[k];
      t0 -= L0[k] * c;
      t1 -= L1[k] * c;
      t2 -= L2[k] * c;
      t3 -= L3[k] * c;
    }
    L0[j] = t0 / l, L1[j] = t1 / l, L2[j] = t2 / l, L3[j] = t3 / l;
  }
  for (; i < n; ++i) {
    double* Li = L + i * n;
    double t = M[i * n + j];
    for (long k = 0; k < j; ++k) t -= Li[k] * Lj[k];
    Li[j] = t / l;
  }
}

DQ_CLONES static int dq_positive_definite(long n, const double* M, double* work) {
  for (long j = 0; j < n; ++j) {
    double* Lj = work + j * n;
    double s = M[j * n + j];
    for (long k = 0; k < j; ++k) s -= Lj[k] * Lj[k];
    if (!(s > 0.0)) return 0;
    const double l = sqrt(s);
    Lj[j] = l;
    dq_cholesky_column(n, j, l, M, work);
  }
  return 1;
}

/* Lower Cholesky factor L of M (n, n) into L (rows; the upper part zero); -1 if M is not
   positive definite. */
DQ_INLINE int dq_cholesky(long n, const double* M, double* L) {
  memset(L, 0, sizeof(double) * n * n);
  for (long j = 0; j < n; ++j) {
    double* Lj = L + j * n;
    double s = M[j * n + j];
    for (long k = 0; k < j; ++k) s -= Lj[k] * Lj[k];
    if (!(s > 0.0)) return -1;
    const double l = sqrt(s);
    Lj[j] = l;
    dq_cholesky_column(n, j, l, M, L);
  }
  return 0;
}

/* Eigen-decomposition M = V diag(w) V' of the symmetric M (n, n): Householder reduction to
   a tridiagonal T = Q' M Q, then implicit symmetric QR steps with Wilkinson's shift on T
   (Golub and Van Loan, Matrix Computations, 8.3), their rotations accumulated into Q. w
   ascending, V's columns the eigenvectors (row-major, V[r n + c]). work: n * n + 3 n
   doubles. Returns 0, or -1 if M is not finite or the QR steps did not converge. */
DQ_CLONES static int dq_eigh(long n, const double* M, double* w, double* V, double* work) {
  double* a = work;
  double *e = work + n * n, *v = e + n, *p = v + n;
  memcpy(a, M, sizeof(double) * n * n);
  /* V holds Q' while the rotations accumulate (row c of V: column c of Q, contiguous), and
     is transposed at the end: the same products and sums as on Q itself */
  memset(V, 0, sizeof(double) * n * n);
  double norm = 0.0;
  for (long i = 0; i < n; ++i) {
    V[i * n + i] = 1.0;
    for (long j = 0; j < n; ++j) norm = fmax(norm, fabs(a[i * n + j]));
  }
  if (!isfinite(norm)) return -1;
  /* Householder: column k below the subdiagonal zeroed by H = I - beta v v' on k + 1.. */
  for (long k = 0; k + 2 < n; ++k) {
    const long L = n - k - 1;
    double xn = 0.0;
    for (long j = 0; j < L; ++j) xn += a[(k + 1 + j) * n + k] * a[(k + 1 + j) * n + k];
    xn = sqrt(xn);
    double tail = 0.0;
    for (long j = 1; j < L; ++j) tail = fmax(tail, fabs(a[(k + 1 + j) * n + k]));
    if (tail == 0.0) continue; /* already tridiagonal in this column */
    const double x0 = a[(k + 1) * n + k];
    const double alpha = x0 >= 0.0 ? -xn : xn;
    for (long j = 0; j < L; ++j) v[j] = a[(k + 1 + j) * n + k];
    v[0] -= alpha;
    double vv = 0.0;
    for (long j = 0; j < L; ++j) vv += v[j] * v[j];
    const double beta = 2.0 / vv;
    /* A22 <- H A22 H = A22 - v w' - w v', p = beta A22 v, w = p - (beta v'p / 2) v */
    long i4 = 0;
    for (; i4 + 4 <= L; i4 += 4) { /* four rows' sums side by side, each in j order */
      const double* a0 = a + (k + 1 + i4) * n + k + 1;
      const double *a1 = a0 + n, *a2 = a1 + n, *a3 = a2 + n;
      double t0 = 0.0, t1 = 0.0, t2 = 0.0, t3 = 0.0;
      for (long j = 0; j < L; ++j) {
        const double vj = v[j];
        t0 += a0[j] * vj;
        t1 += a1[j] * vj;
        t2 += a2[j] * vj;
        t3 += a3[j] * vj;
      }
      p[i4] = beta * t0, p[i4 + 1] = beta * t1, p[i4 + 2] = beta * t2, p[i4 + 3] = beta * t3;
    }
    for (; i4 < L; ++i4) {
      const double* ai = a + (k + 1 + i4) * n + k + 1;
      double t = 0.0;
      for (long j = 0; j < L; ++j) t += ai[j] * v[j];
      p[i4] = beta * t;
    }
    double vp = 0.0;
    for (long i = 0; i < L; ++i) vp += v[i] * p[i];
    const double K = 0.5 * beta * vp;
    for (long i = 0; i < L; ++i) p[i] -= K * v[i];
    for (long i = 0; i < L; ++i) {
      double* ai = a + (k + 1 + i) * n + k + 1;
      for (long j = 0; j < L; ++j) ai[j] -= v[i] * p[j] + p[i] * v[j];
    }
    a[(k + 1) * n + k] = a[k * n + k + 1] = alpha;
    for (long j = 1; j < L; ++j) a[(k + 1 + j) * n + k] = a[k * n + k + 1 + j] = 0.0;
    /* Q <- Q H: t_r = beta sum_j Q[r, k + 1 + j] v_j (j ascending), then Q[r, k + 1 + j] -=
       t_r v_j; on Q' (V) row by row of Q', every r at once */
    double* t = e; /* (n scratch: e is filled after the reduction) */
    for (long r = 0; r < n; ++r) t[r] = 0.0;
    for (long j = 0; j < L; ++j) {
      const double* qj = V + (k + 1 + j) * n;
      const double vj = v[j];
      for (long r = 0; r < n; ++r) t[r] += qj[r] * vj;
    }
    for (long r = 0; r < n; ++r) t[r] *= beta;
    for (long j = 0; j < L; ++j) {
      double* qj = V + (k + 1 + j) * n;
      const double vj = v[j];
      for (long r = 0; r < n; ++r) qj[r] -= t[r] * vj;
    }
  }
  for (long i = 0; i < n; ++i) {
    w[i] = a[i * n + i];
    e[i] = i + 1 < n ? a[(i + 1) * n + i] : 0.0;
  }
  /* implicit QR steps on the unreduced blocks [l, m], from the bottom */
  long m = n - 1, steps = 0;
  while (m > 0) {
    for (long i = 0; i < m; ++i)
      if (fabs(e[i]) <= 1e-16 * (fabs(w[i]) + fabs(w[i + 1])) || fabs(e[i]) <= 1e-300 * norm)
        e[i] = 0.0;
    if (e[m - 1] == 0.0) {
      --m;
      continue;
    }
    long l = m - 1;
    while (l > 0 && e[l - 1] != 0.0) --l;
    if (++steps > 60 * n) return -1;
    const double delta = 0.5 * (w[m - 1] - w[m]);
    const double em = e[m - 1];
    const double mu = w[m] - em * em / (delta + (delta >= 0.0 ? 1.0 : -1.0) * hypot(delta, em));
    double x = w[l] - mu, z = e[l], bulge = 0.0;
    for (long k = l; k < m; ++k) {
      if (k > l) x = e[k - 1], z = bulge;
      const double r = hypot(x, z);
      const double c = r > 0.0 ? x / r : 1.0, s = r > 0.0 ? z / r : 0.0;
      if (k > l) e[k - 1] = r;
      const double dk = w[k], ek = e[k], dk1 = w[k + 1];
      w[k] = c * c * dk + 2.0 * c * s * ek + s * s * dk1;
      e[k] = -c * s * dk + (c * c - s * s) * ek + c * s * dk1;
      w[k + 1] = s * s * dk - 2.0 * c * s * ek + c * c * dk1;
      if (k + 1 < m) {
        bulge = s * e[k + 1];
        e[k + 1] *= c;
      }
      double *q0 = V + k * n, *q1 = q0 + n; /* Q <- Q P' on columns k, k + 1 (rows of Q') */
      for (long rr = 0; rr < n; ++rr) {
        const double qa = q0[rr], qb = q1[rr];
        q0[rr] = c * qa + s * qb;
        q1[rr] = -s * qa + c * qb;
      }
    }
  }
  /* ascending, the vectors with them (selection sort: n is small) */
  for (long i = 0; i < n; ++i) {
    long best = i;
    for (long j = i + 1; j < n; ++j)
      if (w[j] < w[best]) best = j;
    if (best != i) {
      const double t = w[i];
      w[i] = w[best];
      w[best] = t;
      double *qi = V + i * n, *qb = V + best * n;
      for (long r = 0; r < n; ++r) {
        const double q = qi[r];
        qi[r] = qb[r];
        qb[r] = q;
      }
    }
  }
  for (long r = 0; r < n; ++r) /* Q' to Q */
    for (long c = r + 1; c < n; ++c) {
      const double q = V[r * n + c];
      V[r * n + c] = V[c * n + r];
      V[c * n + r] = q;
    }
  return 0;
}

/* dq_eigh for the tests: 0 or -1 (-3 out of memory). */
CASADI_SYMBOL_EXPORT int lfm_dense_eigh(long n, const double* M, double* w, double* V) {
  double* work = malloc(sizeof(double) * (size_t)(n * n + 3 * n + 1));
  if (!work) return -3;
  const int code = dq_eigh(n, M, w, V, work);
  free(work);
  return code;
}

/* out (n, n) = V diag(f(w)) V' with f(w) = max(w, floor), or max(|w|, floor) if absolute. */
DQ_CLONES static void dq_rebuild(long n, const double* w, const double* V, double floor,
                                 int absolute, double* out) {
  double* f = malloc(sizeof(double) * (size_t)(n * n + n + 1));
  if (!f) { /* (out of memory: the plain loops) */
    for (long r = 0; r < n; ++r)
      for (long c = 0; c <= r; ++c) {
        double s = 0.0;
        for (long k = 0; k < n; ++k) {
          const double wk = absolute ? fabs(w[k]) : w[k];
          s += V[r * n + k] * (wk > floor ? wk : floor) * V[c * n + k];
        }
        out[r * n + c] = out[c * n + r] = s;
      }
    return;
  }
  double* VF = f + n; /* VF[r, k] = V[r, k] f(w_k): the same first product */
  for (long k = 0; k < n; ++k) {
    const double wk = absolute ? fabs(w[k]) : w[k];
    f[k] = wk > floor ? wk : floor;
  }
  for (long r = 0; r < n; ++r)
    for (long k = 0; k < n; ++k) VF[r * n + k] = V[r * n + k] * f[k];
  for (long r = 0; r < n; ++r) {
    const double* vf = VF + r * n;
    long c = 0;
    for (; c + 4 <= r + 1; c += 4) { /* four sums side by side, each in k order */
      const double *v0 = V + c * n, *v1 = v0 + n, *v2 = v1 + n, *v3 = v2 + n;
      double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
      for (long k = 0; k < n; ++k) {
        const double x = vf[k];
        s0 += x * v0[k];
        s1 += x * v1[k];
        s2 += x * v2[k];
        s3 += x * v3[k];
      }
      out[r * n + c] = out[c * n + r] = s0;
      out[r * n + c + 1] = out[(c + 1) * n + r] = s1;
      out[r * n + c + 2] = out[(c + 2) * n + r] = s2;
      out[r * n + c + 3] = out[(c + 3) * n + r] = s3;
    }
    for (; c <= r; ++c) {
      const double* vc = V + c * n;
      double s = 0.0;
      for (long k = 0; k < n; ++k) s += vf[k] * vc[k];
      out[r * n + c] = out[c * n + r] = s;
    }
  }
  free(f);
}

/* ------------------------------------------------------------------ the QP without slacks

   min x'H x / 2 + g'x  over  lo <= x <= hi  and  A x <= b, H positive definite, by the dual
   active-set method of Goldfarb and Idnani (Math. Programming 27, 1983): start at the
   unconstrained minimum, add the most violated constraint, step in the primal and dual
   space until it is active, dropping the constraints whose multiplier reaches zero on the
   way. The factorisation J = L^-T Q, R of the active normals is updated by Givens rotations.
   J is kept transposed (JT, row i: column i of J), so that a rotation of two columns and the
   projections run along contiguous memory (the same products and sums as on J itself).
   Each constraint k is written c_k'x >= e_k: a row (k < m) as -a_k'x >= -b_k, an upper
   bound (m <= k < m + n) as -x_j >= -hi_j, a lower bound as x_j >= lo_j. */

typedef struct {
  long n, m;
  const double *A, *b, *lo, *hi;
} dq_cons_t;

/* The value c_k'x - e_k (>= 0: satisfied) of constraint k at x. */
DQ_INLINE double dq_slack(const dq_cons_t* c, long k, const double* x) {
  const long n = c->n;
  if (k < c->m) {
    const double* a = c->A + k * n;
    double s = 0.0;
    for (long j = 0; j < n; ++j) s += a[j] * x[j];
    return c->b[k] - s;
  }
  if (k < c->m + n) return c->hi[k - c->m] - x[k - c->m];
  return x[k - c->m - n] - c->lo[k - c->m - n];
}

/* out[k] = dq_slack(c, k, x) of the rows k < m neither skipped nor active, four rows at a
   time (their sums side by side, each in dq_slack's order); rows: m longs of scratch. */
DQ_INLINE void dq_row_slacks(const dq_cons_t* c, const unsigned char* skip,
                          const unsigned char* is_active, const double* x, long* rows,
                          double* out) {
  const long n = c->n;
  long cnt = 0;
  for (long k = 0; k < c->m; ++k)
    if (!skip[k] && !is_active[k]) rows[cnt++] = k;
  long e = 0;
  for (; e + 4 <= cnt; e += 4) {
    const long k0 = rows[e], k1 = rows[e + 1], k2 = rows[e + 2], k3 = rows[e + 3];
    const double *a0 = c->A + k0 * n, *a1 = c->A + k1 * n, *a2 = c->A + k2 * n;
    const double* a3 = c->A + k3 * n;
    double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
    for (long j = 0; j < n; ++j) {
      const double xj = x[j];
      s0 += a0[j] * xj;
      s1 += a1[j] * xj;
      s2 += a2[j] * xj;
      s3 += a3[j] * xj;
    }
    out[k0] = c->b[k0] - s0, out[k1] = c->b[k1] - s1;
    out[k2] = c->b[k2] - s2, out[k3] = c->b[k3] - s3;
  }
  for (; e < cnt; ++e) out[rows[e]] = dq_slack(c, rows[e], x);
}

/* d = J' c_k (JT = J' (n, n) row-major); nz: n longs of scratch. Each d[i] sums its terms
   over r ascending, the zeros of the row skipped. */
DQ_INLINE void dq_project(const dq_cons_t* c, long k, const double* JT, double* d, long* nz) {
  const long n = c->n;
  if (k < c->m) {
    const double* a = c->A + k * n;
    long cnt = 0;
    for (long r = 0; r < n; ++r)
      if (a[r] != 0.0) nz[cnt++] = r;
    long i = 0;
    for (; i + 4 <= n; i += 4) { /* four independent sums at a time */
      const double *J0 = JT + i * n, *J1 = J0 + n, *J2 = J1 + n, *J3 = J2 + n;
      double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
      for (long e = 0; e < cnt; ++e) {
        const long r = nz[e];
        const double ar = a[r];
        s0 -= ar * J0[r];
        s1 -= ar * J1[r];
        s2 -= ar * J2[r];
        s3 -= ar * J3[r];
      }
      d[i] = s0, d[i + 1] = s1, d[i + 2] = s2, d[i + 3] = s3;
    }
    for (; i < n; ++i) {
      const double* Ji = JT + i * n;
      double s0 = 0.0;
      for (long e = 0; e < cnt; ++e) s0 -= a[nz[e]] * Ji[nz[e]];
      d[i] = s0;
    }
  } else if (k < c->m + n) {
    const long r = k - c->m;
    for (long i = 0; i < n; ++i) d[i] = -JT[i * n + r];
  } else {
    const long r = k - c->m - n;
    for (long i = 0; i < n; ++i) d[i] = JT[i * n + r];
  }
}

/* A Givens rotation of columns i and i + 1 of J (rows of JT): (J_i, J_i+1) <- (c J_i + s
   J_i+1, -s J_i + c J_i+1). */
DQ_INLINE void dq_rotate_columns(long n, double* JT, long i, double c, double s) {
  double *Ji = JT + i * n, *Jj = Ji + n;
  for (long r = 0; r < n; ++r) {
    const double a = Ji[r], b = Jj[r];
    Ji[r] = c * a + s * b;
    Jj[r] = -s * a + c * b;
  }
}

/* Drop active constraint l of q: R (n, n) row-major loses column l and is made upper
   triangular again by rotations, applied to J's columns too. */
DQ_INLINE void dq_drop(long n, long q, long l, double* R, double* J, long* act, double* u,
                    unsigned char* is_active) {
  is_active[act[l]] = 0;
  for (long c = l; c + 1 < q; ++c) {
    for (long r = 0; r < n; ++r) R[r * n + c] = R[r * n + c + 1];
    act[c] = act[c + 1];
    u[c] = u[c + 1];
  }
  for (long r = 0; r < n; ++r) R[r * n + q - 1] = 0.0;
  for (long j = l; j + 1 < q; ++j) { /* zero R[j + 1, j] */
    const double a = R[j * n + j], b = R[(j + 1) * n + j];
    const double h = hypot(a, b);
    if (h == 0.0) continue;
    const double c = a / h, s = b / h;
    R[j * n + j] = h;
    R[(j + 1) * n + j] = 0.0;
    for (long k = j + 1; k + 1 < q; ++k) {
      const double x = R[j * n + k], y = R[(j + 1) * n + k];
      R[j * n + k] = c * x + s * y;
      R[(j + 1) * n + k] = -s * x + c * y;
    }
    dq_rotate_columns(n, J, j, c, s);
  }
}

/* Add constraint p with d = J' c_p: rotations zero d[q + 1 ..], applied to J's columns; d[0..q]
   becomes column q of R. */
DQ_INLINE void dq_add(long n, long q, double* d, double* R, double* J) {
  for (long j = n - 1; j > q; --j) {
    const double a = d[j - 1], b = d[j];
    if (b == 0.0) continue;
    const double h = hypot(a, b);
    const double c = a / h, s = b / h;
    d[j - 1] = h;
    d[j] = 0.0;
    dq_rotate_columns(n, J, j - 1, c, s);
  }
  for (long r = 0; r <= q; ++r) R[r * n + q] = d[r];
}

enum { DQ_SOLVED = 0, DQ_INFEASIBLE = 1, DQ_ITERATIONS = 2, DQ_NOT_CONVEX = 3, DQ_MEMORY = 4 };

/* One full or partial step towards the violated constraint p (Goldfarb-Idnani step 2, until p
   is added or the problem is found infeasible); returns -1 (infeasible), else the
   constraints added (0 or 1), and counts the rotations' steps in *steps. */
DQ_INLINE int dq_step_to(const dq_cons_t* cons, long p, double* x, double* J, double* R,
                      long* act, unsigned char* is_active, double* u, long* q_io, double* d,
                      double* z, double* r, long* nz, long max_steps, long* steps) {
  const long n = cons->n;
  long q = *q_io;
  double uq = 0.0; /* the multiplier of p */
  for (;;) {
    if (++*steps > max_steps) return -2;
    dq_project(cons, p, J, d, nz);
    double d2 = 0.0, dn = 0.0;
    for (long i = 0; i < n; ++i) {
      dn += d[i] * d[i];
      if (i >= q) d2 += d[i] * d[i];
    }
    const int primal = d2 > 1e-20 * dn; /* c_p independent of the active normals */
    for (long i = q - 1; i >= 0; --i) { /* r = R^-1 d[0..q) */
      double s = d[i];
      for (long k = i + 1; k < q; ++k) s -= R[i * n + k] * r[k];
      r[i] = s / R[i * n + i];
    }
    double t1 = INFINITY;
    long l = -1;
    for (long j = 0; j < q; ++j)
      if (r[j] > 0.0 && u[j] / r[j] < t1) t1 = u[j] / r[j], l = j;
    double t2 = INFINITY;
    if (primal) {
      for (long i = 0; i < n; ++i) z[i] = 0.0; /* z = J[:, q:] d[q:], k ascending */
      for (long k = q; k < n; ++k) {
        const double* Jk = J + k * n;
        const double dk = d[k];
        for (long i = 0; i < n; ++i) z[i] += Jk[i] * dk;
      }
      t2 = -dq_slack(cons, p, x) / d2;
      if (t2 < 0.0) t2 = 0.0;
    }
    const double t = t1 < t2 ? t1 : t2;
    if (!(t < INFINITY)) return -1;
    for (long j = 0; j < q; ++j) u[j] -= t * r[j];
    uq += t;
    if (primal)
      for (long i = 0; i < n; ++i) x[i] += t * z[i];
    if (primal && t2 <= t1) { /* full step: p becomes active */
      dq_add(n, q, d, R, J);
      act[q] = p;
      is_active[p] = 1;
      u[q] = uq;
      *q_io = q + 1;
      return 1;
    }
    dq_drop(n, q, l, R, J, act, u, is_active); /* partial step: constraint l leaves */
    --q;
    *q_io = q;
  }
}

/* Solves min x'Hx/2 + g'x, lo <= x <= hi (infinite: none), A x <= b (rows with b = +inf
   skipped): x (n), the rows' multipliers lam (m, >= 0; zero where inactive); tol: the
   violation a constraint may keep. Returns DQ_SOLVED, DQ_INFEASIBLE, DQ_ITERATIONS,
   DQ_NOT_CONVEX or DQ_MEMORY. */
DQ_CLONES CASADI_SYMBOL_EXPORT int lfm_dense_qp(long n, long m, const double* H, const double* g,
    const double* lo, const double* hi, const double* A, const double* b, double tol,
    long max_steps, double* x, double* lam, long* steps_out) {
  const long K = m + 2 * n;
  double* buf = malloc(sizeof(double) * (size_t)(3 * n * n + 4 * n + K + 1));
  long* act = malloc(sizeof(long) * (size_t)(2 * n + 1));
  unsigned char* skip = calloc((size_t)(2 * K + 1), 1);
  if (!buf || !act || !skip) {
    free(buf);
    free(act);
    free(skip);
    return DQ_MEMORY;
  }
  long* nz = act + n;                  /* (n) scratch of dq_project */
  unsigned char* is_active = skip + K; /* (K) constraint k is in act[0..q) */
  double *L = buf, *J = buf + n * n, *R = buf + 2 * n * n, *d = buf + 3 * n * n;
  double *z = d + n, *r = z + n, *u = r + n, *row_slack = u + n;
  long* rows = malloc(sizeof(long) * (size_t)(m + 1));
  if (!rows) {
    free(buf);
    free(act);
    free(skip);
    return DQ_MEMORY;
  }
  int status = DQ_SOLVED;
  long q = 0, steps = 0;
  dq_cons_t cons = {n, m, A, b, lo, hi};
  for (long k = 0; k < m; ++k) skip[k] = !(b[k] < INFINITY);
  for (long j = 0; j < n; ++j) {
    skip[m + j] = !(fabs(hi[j]) < 1e30);
    skip[m + n + j] = !(fabs(lo[j]) < 1e30);
  }
  if (dq_cholesky(n, H, L)) {
    status = DQ_NOT_CONVEX;
  } else {
    /* J = L^-T: column i of L^-1 solves L y = e_i, into row i of Y (in R's room), so
       Y[i, rr] = (L^-1)[rr, i] = J[i, rr]; then JT (in J's room) its transpose */
    double* Y = R;
    memset(Y, 0, sizeof(double) * n * n);
    for (long i = 0; i < n; ++i) { /* (y_k = 0 for k < i: those terms change no sum) */
      for (long rr = i; rr < n; ++rr) {
        double s = rr == i ? 1.0 : 0.0;
        for (long k = i; k < rr; ++k) s -= L[rr * n + k] * Y[i * n + k];
        Y[i * n + rr] = s / L[rr * n + rr];
      }
    }
    for (long i = 0; i < n; ++i)
      for (long k = 0; k < n; ++k) J[k * n + i] = Y[i * n + k];
    for (long i = 0; i < n; ++i) { /* x = -J J' g (each sum over k, then i, ascending) */
      const double* Ji = J + i * n;
      double s = 0.0;
      for (long k = 0; k < n; ++k) s += Ji[k] * g[k];
      d[i] = s;
    }
    for (long k = 0; k < n; ++k) x[k] = 0.0;
    for (long i = 0; i < n; ++i) {
      const double* Ji = J + i * n;
      const double di = d[i];
      for (long k = 0; k < n; ++k) x[k] += Ji[k] * di;
    }
    for (long k = 0; k < n; ++k) x[k] = -x[k];
    memset(R, 0, sizeof(double) * n * n);
    for (;;) {
      dq_row_slacks(&cons, skip, is_active, x, rows, row_slack);
      long p = -1;
      double worst = -tol;
      for (long k = 0; k < K; ++k) {
        if (skip[k] || is_active[k]) continue;
        const double s = k < m ? row_slack[k] : dq_slack(&cons, k, x);
        if (s < worst || s != s) worst = s, p = k;
        if (s != s) break;
      }
      if (p < 0) break;
      if (worst != worst) {
        status = DQ_INFEASIBLE;
        break;
      }
      const int added =
          dq_step_to(&cons, p, x, J, R, act, is_active, u, &q, d, z, r, nz, max_steps, &steps);
      if (added == -1) {
        status = DQ_INFEASIBLE;
        break;
      }
      if (added == -2) {
        status = DQ_ITERATIONS;
        break;
      }
    }
  }
  for (long k = 0; k < m; ++k) lam[k] = 0.0;
  if (status == DQ_SOLVED)
    for (long a = 0; a < q; ++a)
      if (act[a] < m) lam[act[a]] = u[a] > 0.0 ? u[a] : 0.0;
  if (steps_out) *steps_out = steps;
  free(rows);
  free(buf);
  free(act);
  free(skip);
  return status;
}
