#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "clones.h"

static inline double dotn(long n, const double* a, const double* b) {
  double s = 0.0;
#pragma omp simd reduction(+ : s)
  for (long p = 0; p < n; ++p) s += a[p] * b[p];
  return s;
}

static inline double amax(long n, const double* a) {
  double s = 0.0;
  for (long p = 0; p < n; ++p) s = fmax(s, fabs(a[p]));
  return s;
}

/* The lower triangle of M (n, n) += sum over the rows y of Y (rows, n) of y y', four rows
   of Y at a time, two rows of M at a time (they share the loads of y[q]). Row i of Y is zero
   from wy[i] on (the rows of the QP's early steps: the inputs' sensitivities are causal),
   so four rows touch only the block of M up to their widest: the same sums (without the
   zeros' terms), in O(w^2) instead of O(n^2). */
static void add_gram(long n, long rows, const double* Y, const long* wy, double* M) {
  long i = 0;
  for (; i + 4 <= rows; i += 4) {
    const double *y0 = Y + i * n, *y1 = y0 + n, *y2 = y1 + n, *y3 = y2 + n;
    const long w = wy[i] > wy[i + 1] ? wy[i] : wy[i + 1];
    const long w2 = wy[i + 2] > wy[i + 3] ? wy[i + 2] : wy[i + 3];
    /* (even, so that the rows of M pair as over the whole width: the same sums) */
    const long wide = w > w2 ? w : w2, wb = wide + (wide & 1) < n ? wide + (wide & 1) : n;
    long p = 0;
    for (; p + 2 <= wb; p += 2) {
      const double a0 = y0[p], a1 = y1[p], a2 = y2[p], a3 = y3[p];
      const double b0 = y0[p + 1], b1 = y1[p + 1], b2 = y2[p + 1], b3 = y3[p + 1];
      double *Mp = M + p * n, *Mq = Mp + n;
      for (long q = 0; q <= p; ++q) {
        const double c0 = y0[q], c1 = y1[q], c2 = y2[q], c3 = y3[q];
        Mp[q] += a0 * c0 + a1 * c1 + a2 * c2 + a3 * c3;
        Mq[q] += b0 * c0 + b1 * c1 + b2 * c2 + b3 * c3;
      }
      Mq[p + 1] += b0 * b0 + b1 * b1 + b2 * b2 + b3 * b3;
    }
    for (; p < wb; ++p) {
      const double a0 = y0[p], a1 = y1[p], a2 = y2[p], a3 = y3[p];
      double* Mp = M + p * n;
      for (long q = 0; q <= p; ++q) Mp[q] += a0 * y0[q] + a1 * y1[q] + a2 * y2[q] + a3 * y3[q];
    }
  }
  for (; i < rows; ++i) {
    const double* y0 = Y + i * n;
    for (long p = 0; p < wy[i]; ++p) {
      double* Mp = M + p * n;
      for (long q = 0; q <= p; ++q) Mp[q] += y0[p] * y0[q];
    }
  }
}

/* Cholesky factor of M in its lower triangle, in place; -1 if M is not positive definite. */
static int cholesky(long n, double* M) {
  for (long j = 0; j < n; ++j) {
    double* Mj = M + j * n;
    const double s = Mj[j] - dotn(j, Mj, Mj);
    if (!(s > 0.0)) return -1;
    const double l = sqrt(s);
    Mj[j] = l;
    for (long i = j + 1; i < n; ++i) {
      double* Mi = M + i * n;
      Mi[j] = (Mi[j] - dotn(j, Mi, Mj)) / l;
    }
  }
  return 0;
}

/* x = (L L')^{-1} x. */
static void cholesky_solve(long n, const double* L, double* x) {
  for (long i = 0; i < n; ++i) x[i] = (x[i] - dotn(i, L + i * n, x)) / L[i * n + i];
  for (long i = n - 1; i >= 0; --i) { /* by rows of L: x[k] -= L[i, k] x[i], k < i */
    x[i] /= L[i * n + i];
    const double* Li = L + i * n;
    for (long k = 0; k < i; ++k) x[k] -= Li[k] * x[i];
  }
}

typedef struct {
  long n, m, G;
  const double *H, *A, *reg;
  const long* col;
  const double* D; /* row scalings: rows (m), slack bounds (G), upper (n), lower (n) */
  double *T, *k, *abar, *M, *Y;
  const long *w, *wg; /* each row's width (its entries from there on are zero), each group's */
  long* wy;           /* (m + G) the widths of the rows of Y */
} reduced_t;

/* The reduced matrix M of the scalings D (module docstring), factorised; -1 on failure. */
static int reduce(reduced_t* q) {
  const long n = q->n, m = q->m, G = q->G;
  const double *D = q->D, *DS = q->D + m, *DU = DS + G, *DL = DU + n;
  memset(q->T, 0, sizeof(double) * G);
  memset(q->abar, 0, sizeof(double) * G * n);
  for (long i = 0; i < m; ++i) {
    const long c = q->col[i];
    const double* a = q->A + i * n;
    double* ac = q->abar + c * n;
    q->T[c] += D[i];
    for (long p = 0; p < q->w[i]; ++p) ac[p] += D[i] * a[p];
  }
  for (long c = 0; c < G; ++c) {
    q->k[c] = q->reg[c] + DS[c] + q->T[c];
    if (q->T[c] > 0.0)
      for (long p = 0; p < q->wg[c]; ++p) q->abar[c * n + p] /= q->T[c];
  }
  for (long i = 0; i < m; ++i) { /* rows sqrt(D_i) (a_i - abar_c), zero from the group's width */
    const double r = sqrt(D[i]);
    const long wc = q->wg[q->col[i]];
    const double *a = q->A + i * n, *ac = q->abar + q->col[i] * n;
    double* y = q->Y + i * n;
    for (long p = 0; p < wc; ++p) y[p] = r * (a[p] - ac[p]);
    memset(y + wc, 0, sizeof(double) * (n - wc));
    q->wy[i] = wc;
  }
  long rows = m;
  for (long c = 0; c < G; ++c) { /* then sqrt(T_c e_c / k_c) abar_c */
    if (q->T[c] <= 0.0) continue;
    const double r = sqrt(q->T[c] * (q->reg[c] + DS[c]) / q->k[c]);
    double* y = q->Y + rows * n;
    for (long p = 0; p < q->wg[c]; ++p) y[p] = r * q->abar[c * n + p];
    memset(y + q->wg[c], 0, sizeof(double) * (n - q->wg[c]));
    q->wy[rows] = q->wg[c];
    ++rows;
  }
  for (long p = 0; p < n; ++p) {
    for (long r = 0; r <= p; ++r) q->M[p * n + r] = q->H[p * n + r];
    q->M[p * n + p] += DU[p] + DL[p];
  }
  add_gram(n, rows, q->Y, q->wy, q->M);
  return cholesky(n, q->M);
}

/* The step (dd, ds) of the (d, s) system with right-hand sides (hd, hs), slacks eliminated. */
static void reduced_solve(const reduced_t* q, const double* hd, const double* hs, double* dd,
                          double* ds) {
  const long n = q->n, G = q->G;
  memcpy(dd, hd, sizeof(double) * n);
  for (long c = 0; c < G; ++c) {
    if (q->T[c] <= 0.0) continue;
    const double f = q->T[c] * hs[c] / q->k[c];
    for (long p = 0; p < n; ++p) dd[p] += f * q->abar[c * n + p];
  }
  cholesky_solve(n, q->M, dd);
  for (long c = 0; c < G; ++c) {
    const double t = q->T[c] > 0.0 ? q->T[c] * dotn(n, q->abar + c * n, dd) : 0.0;
    ds[c] = (hs[c] + t) / q->k[c];
  }
}

/* Largest alpha <= 1 with x + alpha dx >= 0. */
static double max_step(long len, const double* x, const double* dx) {
  double a = 1.0;
  for (long i = 0; i < len; ++i)
    if (dx[i] < 0.0 && -x[i] > a * dx[i]) a = -x[i] / dx[i];
  return a;
}

/* Solves the elastic QP (module docstring). H (n, n) row-major, positive definite; g, lo, hi
   (n) (infinite bounds: none); A (m, n) row-major, b (m), col (m) in [0, G): the slack
   column of each row; rho, reg (G): the slacks' linear and quadratic costs. Out: d (n),
   s (G), the rows' multipliers z_rows (m) and the iterations. Returns 0 when solved, -1 at
   the iteration limit, -2 if the reduced matrix is not positive definite, -3 if out of
   memory, -4 on a non-finite residual. */
LFM_CLONES __attribute__((flatten)) int lfm_elastic_qp(long n, long m, long G,
    const double* H, const double* g, const double* lo, const double* hi, const double* A,
    const double* b, const long* col, const double* rho, const double* reg, double eps_abs,
    double eps_rel, double delta, double fraction, long max_iter, double* d, double* s,
    double* z_rows, long* iterations) {
  /* inequalities in blocks: rows (m), slack bounds -s <= 0 (G), d <= hi (n), -d <= -lo (n) */
  const long K = m + G + 2 * n;
  double* buf = calloc((size_t)(10 * K + 2 * G + G * n + n * n + (m + G) * n + 12 * (n + G) + 1),
                       sizeof(double));
  char* has = calloc((size_t)(2 * n + 1), 1);
  long* widths = malloc(sizeof(long) * (size_t)(2 * m + 2 * G + 1));
  if (!buf || !has || !widths) {
    free(buf);
    free(has);
    free(widths);
    return -3;
  }
  /* each row's width (its last nonzero entry + 1), each group's (its rows' widest): the
     reduced matrix skips the zeros beyond (the same sums); the O(m n) loops keep the whole
     rows, whose vectorised bodies and scalar remainders round differently */
  long *w = widths, *wg = widths + m, *wy = widths + m + G;
  for (long c = 0; c < G; ++c) wg[c] = 0;
  for (long i = 0; i < m; ++i) {
    long len = n;
    while (len > 0 && A[i * n + len - 1] == 0.0) --len;
    w[i] = len;
    if (len > wg[col[i]]) wg[col[i]] = len;
  }
  double* p = buf;
  double *v = p, *z = p + K, *D = p + 2 * K, *rp = p + 3 * K, *dv = p + 4 * K;
  double *dz = p + 5 * K, *rc = p + 6 * K, *dva = p + 7 * K, *dza = p + 8 * K, *u = p + 9 * K;
  p += 10 * K;
  reduced_t q = {n, m, G, H, A, reg, col, D, p, p + G, p + 2 * G, NULL, NULL, w, wg, wy};
  p += 2 * G + G * n;
  q.M = p;
  p += n * n;
  q.Y = p;
  p += (m + G) * n;
  double *rd = p, *rs = p + n, *hd = p + n + G, *hs = p + 2 * n + G;
  double *dd = p + 2 * (n + G), *ds = p + 3 * n + 2 * G, *sd = p + 3 * (n + G);
  double *ss = p + 4 * n + 3 * G, *Hd = p + 4 * (n + G);
  char *hasU = has, *hasL = has + n;
  long active = m + G;
  for (long j = 0; j < n; ++j) {
    hasU[j] = isfinite(hi[j]);
    hasL[j] = isfinite(lo[j]);
    active += hasU[j] + hasL[j];
  }
  /* Start: (H + C'C) x = -q + C'e with unit scalings, v = e - C x, z = -v, each shifted. */
  for (long k = 0; k < K; ++k) D[k] = 1.0;
  for (long j = 0; j < n; ++j) {
    if (!hasU[j]) D[m + G + j] = 0.0;
    if (!hasL[j]) D[m + G + n + j] = 0.0;
  }
  int status = reduce(&q) ? -2 : -1;
  long it = 0;
  if (status == -1) {
    for (long j = 0; j < n; ++j)
      hd[j] = -g[j] + (hasU[j] ? hi[j] : 0.0) + (hasL[j] ? lo[j] : 0.0);
    for (long c = 0; c < G; ++c) hs[c] = -rho[c];
    for (long i = 0; i < m; ++i) {
      const double* a = A + i * n;
      for (long j = 0; j < n; ++j) hd[j] += b[i] * a[j];
      hs[col[i]] -= b[i];
    }
    reduced_solve(&q, hd, hs, d, s);
    for (long i = 0; i < m; ++i) v[i] = b[i] - dotn(n, A + i * n, d) + s[col[i]];
    for (long c = 0; c < G; ++c) v[m + c] = s[c];
    for (long j = 0; j < n; ++j) {
      v[m + G + j] = hasU[j] ? hi[j] - d[j] : 1.0;
      v[m + G + n + j] = hasL[j] ? d[j] - lo[j] : 1.0;
    }
    double vmin = INFINITY, vmax = -INFINITY;
    for (long k = 0; k < K; ++k) vmin = fmin(vmin, v[k]), vmax = fmax(vmax, v[k]);
    const double vshift = vmin < 1.0 ? 1.0 - vmin : 0.0, zshift = vmax > -1.0 ? 1.0 + vmax : 0.0;
    for (long k = 0; k < K; ++k) { /* z = -v, shifted to >= 1 */
      z[k] = -v[k] + zshift;
      v[k] += vshift;
    }
    for (long j = 0; j < n; ++j) {
      if (!hasU[j]) v[m + G + j] = 1.0, z[m + G + j] = 0.0;
      if (!hasL[j]) v[m + G + n + j] = 1.0, z[m + G + n + j] = 0.0;
    }
  }
  for (; status == -1 && it <= max_iter; ++it) {
    /* Residuals, with the sums of their terms' magnitudes (sd, ss) as their scales. */
    for (long j = 0; j < n; ++j) {
      double h = 0.0, a = fabs(g[j]);
      for (long r = 0; r < n; ++r) {
        h += H[j * n + r] * d[r];
        a += fabs(H[j * n + r] * d[r]);
      }
      Hd[j] = h;
      rd[j] = h + g[j];
      if (hasU[j]) rd[j] += z[m + G + j], a += z[m + G + j];
      if (hasL[j]) rd[j] -= z[m + G + n + j], a += z[m + G + n + j];
      sd[j] = a;
    }
    for (long c = 0; c < G; ++c) {
      rs[c] = reg[c] * s[c] + rho[c] - z[m + c];
      ss[c] = fabs(reg[c] * s[c]) + fabs(rho[c]) + z[m + c];
    }
    double scale_p = 0.0;
    for (long i = 0; i < m; ++i) {
      const double* a = A + i * n;
      double ad = 0.0, aa = 0.0;
      for (long j = 0; j < n; ++j) {
        rd[j] += z[i] * a[j];
        sd[j] += fabs(z[i] * a[j]);
        ad += a[j] * d[j];
        aa += fabs(a[j] * d[j]);
      }
      rs[col[i]] -= z[i];
      ss[col[i]] += z[i];
      rp[i] = ad - s[col[i]] - b[i] + v[i];
      scale_p = fmax(scale_p, aa + fabs(s[col[i]]) + fabs(b[i]) + v[i]);
    }
    for (long c = 0; c < G; ++c) rp[m + c] = v[m + c] - s[c];
    for (long j = 0; j < n; ++j) {
      rp[m + G + j] = hasU[j] ? d[j] - hi[j] + v[m + G + j] : 0.0;
      rp[m + G + n + j] = hasL[j] ? lo[j] - d[j] + v[m + G + n + j] : 0.0;
      if (hasU[j]) scale_p = fmax(scale_p, fabs(d[j]) + fabs(hi[j]));
      if (hasL[j]) scale_p = fmax(scale_p, fabs(d[j]) + fabs(lo[j]));
    }
    /* The duality gap against the objective's terms (quadratic, linear, dual). */
    double gap = 0.0, quad = 0.0, lin = 0.0, dual = 0.0;
    for (long k = 0; k < K; ++k) gap += v[k] * z[k];
    for (long j = 0; j < n; ++j) {
      quad += d[j] * Hd[j];
      lin += g[j] * d[j];
      if (hasU[j]) dual += hi[j] * z[m + G + j];
      if (hasL[j]) dual -= lo[j] * z[m + G + n + j];
    }
    for (long c = 0; c < G; ++c) {
      quad += reg[c] * s[c] * s[c];
      lin += rho[c] * s[c];
    }
    for (long i = 0; i < m; ++i) dual += b[i] * z[i];
    if (!isfinite(gap + amax(n, rd) + amax(G, rs) + amax(K, rp))) {
      status = -4;
      break;
    }
    if (amax(n, rd) <= eps_abs + eps_rel * amax(n, sd)
        && amax(G, rs) <= eps_abs + eps_rel * amax(G, ss)
        && amax(K, rp) <= eps_abs + eps_rel * scale_p
        && gap <= 1e-8 + 1e-9 * fmax(fabs(quad), fmax(fabs(lin), fabs(dual)))) {
      status = 0;
      break;
    }
    if (it == max_iter) break;
    const double mu = gap / (double)active;
    for (long k = 0; k < K; ++k) D[k] = z[k] / (v[k] + delta * z[k]);
    if (reduce(&q)) {
      status = -2;
      break;
    }
    /* Predictor (rc = z v), then corrector (rc = z v + dza dva - sigma mu). */
    double alpha = 1.0;
    for (int phase = 0; phase < 2; ++phase) {
      double sigma_mu = 0.0;
      if (phase == 1) {
        double mua = 0.0;
        for (long k = 0; k < K; ++k) mua += (v[k] + alpha * dva[k]) * (z[k] + alpha * dza[k]);
        mua /= (double)active;
        sigma_mu = pow(mua / mu, 3.0) * mu;
      }
      for (long k = 0; k < K; ++k) {
        rc[k] = z[k] * v[k] - sigma_mu + (phase == 1 ? dza[k] * dva[k] : 0.0);
        u[k] = (z[k] * rp[k] - rc[k]) / (v[k] + delta * z[k]);
      }
      for (long j = 0; j < n; ++j) {
        if (!hasU[j]) u[m + G + j] = 0.0;
        if (!hasL[j]) u[m + G + n + j] = 0.0;
      }
      /* right-hand sides -r_dual - C' u */
      for (long j = 0; j < n; ++j) hd[j] = -rd[j] - u[m + G + j] + u[m + G + n + j];
      for (long c = 0; c < G; ++c) hs[c] = -rs[c] + u[m + c];
      for (long i = 0; i < m; ++i) {
        const double* a = A + i * n;
        for (long j = 0; j < n; ++j) hd[j] -= u[i] * a[j];
        hs[col[i]] += u[i];
      }
      reduced_solve(&q, hd, hs, dd, ds);
      /* C (dd, ds), then dz = (z (rp + C dx) - rc) / (v + delta z) and dv from the primal
         row, dv = -rp - C dx + delta dz. */
      for (long i = 0; i < m; ++i) dv[i] = dotn(n, A + i * n, dd) - ds[col[i]];
      for (long c = 0; c < G; ++c) dv[m + c] = -ds[c];
      for (long j = 0; j < n; ++j) dv[m + G + j] = dd[j], dv[m + G + n + j] = -dd[j];
      for (long k = 0; k < K; ++k) {
        const double cx = dv[k];
        dz[k] = (z[k] * (rp[k] + cx) - rc[k]) / (v[k] + delta * z[k]);
        dv[k] = -rp[k] - cx + delta * dz[k];
      }
      for (long j = 0; j < n; ++j) {
        if (!hasU[j]) dv[m + G + j] = dz[m + G + j] = 0.0;
        if (!hasL[j]) dv[m + G + n + j] = dz[m + G + n + j] = 0.0;
      }
      alpha = fmin(max_step(K, v, dv), max_step(K, z, dz));
      if (phase == 0) {
        memcpy(dva, dv, sizeof(double) * K);
        memcpy(dza, dz, sizeof(double) * K);
      }
    }
    const double step = fmin(1.0, fraction * alpha);
    for (long j = 0; j < n; ++j) d[j] += step * dd[j];
    for (long c = 0; c < G; ++c) s[c] += step * ds[c];
    for (long k = 0; k < K; ++k) {
      v[k] += step * dv[k];
      z[k] += step * dz[k];
    }
  }
  memcpy(z_rows, z, sizeof(double) * m);
  *iterations = it;
  free(buf);
  free(has);
  free(widths);
  return status;
}
