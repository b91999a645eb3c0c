/* lfm_controller.c: the exported agent's step (lfm_controller.h) around the compiled SQP.

   The same steps as the Python agent (controllers/agents/mpc.py, MPCAgent.act): the estimate
   (the unscented Kalman filter of controllers/estimators/ukf.py, restarted when a measurement
   is a 1e-6 tail event for it), the scenarios (the latent force's mean forecast H A^k z, or
   Ns sampled paths z_k+1 = A z_k + Q_factor xi from the estimate's mean or from draws of the
   estimate), the back-off k_j sqrt(dg_j' Sigma_x dg_j), the solve, and the choice of the
   input. The draws use this file's own generator (xoshiro256** seeded by splitmix64,
   normals by Marsaglia's polar method): the same distributions as NumPy's, other numbers. */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "lfm_controller.h"
#include "lfm_internal.h"

#define CFG (&lfm_exported_config)

struct lfm_controller {
  lfm_sqp* sqp;
  uint64_t rng[4];
  int has_normal;
  double normal;
  int started;
  double mean[LFM_D], cov[LFM_D * LFM_D];
  double x0[LFM_NS * LFM_NX], W[LFM_NS * LFM_N * LFM_NW], backoff[LFM_N * LFM_NG + 1];
  int has_backoff;
  double plan[LFM_N * LFM_NU];
  long plan_at; /* the plan's next input; LFM_N: none left */
  double u_prev[LFM_NU];
  double stats[ST_COUNT]; /* sqp_interface.h */
  lfm_info info;
};

/* ------------------------------------------------------------------ random numbers */

static uint64_t splitmix64(uint64_t* x) {
  uint64_t z = (*x += 0x9e3779b97f4a7c15ULL);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

static uint64_t rotl(uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }

static uint64_t next_u64(uint64_t* s) { /* xoshiro256** (Blackman and Vigna) */
  const uint64_t result = rotl(s[1] * 5, 7) * 9, t = s[1] << 17;
  s[2] ^= s[0];
  s[3] ^= s[1];
  s[1] ^= s[2];
  s[0] ^= s[3];
  s[2] ^= t;
  s[3] = rotl(s[3], 45);
  return result;
}

static double uniform_pm1(uint64_t* s) { /* in (-1, 1) */
  return ((double)(next_u64(s) >> 11) + 0.5) * (2.0 / 9007199254740992.0) - 1.0;
}

static double standard_normal(lfm_controller* c) { /* Marsaglia's polar method */
  if (c->has_normal) {
    c->has_normal = 0;
    return c->normal;
  }
  double a, b, r;
  do {
    a = uniform_pm1(c->rng);
    b = uniform_pm1(c->rng);
    r = a * a + b * b;
  } while (r >= 1.0 || r == 0.0);
  const double f = sqrt(-2.0 * log(r) / r);
  c->normal = b * f;
  c->has_normal = 1;
  return a * f;
}

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* ------------------------------------------------------------------ life cycle */

lfm_controller* lfm_controller_new(void) {
  lfm_controller* c = calloc(1, sizeof(lfm_controller));
  if (!c) return NULL;
  c->sqp = lfm_sqp_new(&CFG->problem, &CFG->options);
  if (!c->sqp || lfm_sqp_stats_count() != ST_COUNT) {
    lfm_sqp_free(c->sqp);
    free(c);
    return NULL;
  }
  lfm_controller_reset(c, 0);
  return c;
}

void lfm_controller_free(lfm_controller* c) {
  if (!c) return;
  lfm_sqp_free(c->sqp);
  free(c);
}

void lfm_controller_reset(lfm_controller* c, uint64_t seed) {
  uint64_t x = seed;
  for (int i = 0; i < 4; ++i) c->rng[i] = splitmix64(&x);
  c->has_normal = 0;
  c->started = 0;
  c->plan_at = LFM_N;
  c->has_backoff = 0;
  memset(c->u_prev, 0, sizeof(c->u_prev));
  memset(&c->info, 0, sizeof(c->info));
  lfm_sqp_reset(c->sqp);
}

/* ------------------------------------------------------------------ the estimate */

/* S with S S' = P (P (d, d) symmetric PSD): the eigenvectors scaled by the roots of the
   eigenvalues clipped at zero (lfm_env.model.psd_factor). */
static int psd_factor(const double* P, double* S) {
  double w[LFM_D], V[LFM_D * LFM_D];
  if (lfm_dense_eigh(LFM_D, P, w, V)) return 1;
  for (int r = 0; r < LFM_D; ++r)
    for (int j = 0; j < LFM_D; ++j) S[r * LFM_D + j] = V[r * LFM_D + j] * sqrt(fmax(w[j], 0.0));
  return 0;
}

static void ukf_start(lfm_controller* c, const double* y) {
  memset(c->mean, 0, sizeof(c->mean));
  memset(c->cov, 0, sizeof(c->cov));
  for (int m = 0; m < LFM_NX; ++m) {
    c->mean[m] = y[m];
    c->cov[m * (LFM_D + 1)] = CFG->measurement_std[m] * CFG->measurement_std[m];
  }
  for (int a = 0; a < LFM_NP; ++a)
    for (int b = 0; b < LFM_NP; ++b)
      c->cov[(LFM_NX + a) * LFM_D + LFM_NX + b] = CFG->P_inf[a * LFM_NP + b];
  c->started = 1;
}

/* The unscented prediction through one step with the input u (UnscentedKalmanFilter.predict):
   2 d + 1 sigma points mean +- sqrt(d) S_j, the physical step of each by the generated
   library (lfm_step_points) and z+ = A z; 0, or 1 if the factor failed. */
static int ukf_predict(lfm_controller* c, const double* u) {
  enum { D = LFM_D, K = 2 * LFM_D + 1 };
  double S[D * D], pts[D * K], xT[LFM_NX * K], Wp[LFM_NW * K], X[2 * LFM_NX * K];
  if (psd_factor(c->cov, S)) return 1;
  const double root = sqrt((double)D);
  for (int i = 0; i < K; ++i) {
    const int j = (i - 1) % D, sign = i == 0 ? 0 : (i <= D ? 1 : -1);
    for (int r = 0; r < D; ++r) pts[r * K + i] = c->mean[r] + sign * root * S[r * D + j];
  }
  for (int i = 0; i < K; ++i) {
    for (int m = 0; m < LFM_NX; ++m) xT[m * K + i] = pts[m * K + i];
    for (int a = 0; a < LFM_NW; ++a) {
      double w = 0.0;
      for (int b = 0; b < LFM_NP; ++b) w += CFG->H[a * LFM_NP + b] * pts[(LFM_NX + b) * K + i];
      Wp[a * K + i] = w;
    }
  }
  if (lfm_step_points(K, xT, Wp, u, X)) return 1;
  double moved[D * K];
  for (int i = 0; i < K; ++i) {
    for (int m = 0; m < LFM_NX; ++m) moved[m * K + i] = X[(LFM_NX + m) * K + i];
    for (int a = 0; a < LFM_NP; ++a) {
      double z = 0.0;
      for (int b = 0; b < LFM_NP; ++b) z += CFG->A[a * LFM_NP + b] * pts[(LFM_NX + b) * K + i];
      moved[(LFM_NX + a) * K + i] = z;
    }
  }
  const double w = 1.0 / (2.0 * D);
  for (int r = 0; r < D; ++r) {
    double s = 0.0;
    for (int i = 1; i < K; ++i) s += moved[r * K + i];
    c->mean[r] = w * s;
  }
  for (int r = 0; r < D; ++r)
    for (int i = 0; i < K; ++i) moved[r * K + i] -= c->mean[r];
  for (int a = 0; a < D; ++a)
    for (int b = 0; b <= a; ++b) {
      double s = 0.0;
      for (int i = 1; i < K; ++i) s += moved[a * K + i] * moved[b * K + i];
      s = w * s + 2.0 * moved[a * K] * moved[b * K];
      c->cov[a * D + b] = c->cov[b * D + a] = s;
    }
  for (int m = 0; m < LFM_NX; ++m) c->cov[m * (D + 1)] += CFG->process_std[m] * CFG->process_std[m];
  for (int a = 0; a < LFM_NP; ++a)
    for (int b = 0; b < LFM_NP; ++b) c->cov[(LFM_NX + a) * D + LFM_NX + b] += CFG->Q[a * LFM_NP + b];
  return 0;
}

/* x = M^-1 b for the symmetric positive definite M (n, n) by its Cholesky factor (L: work). */
static int spd_solve(int n, const double* M, double* L, double* x) {
  for (int j = 0; j < n; ++j) {
    double s = M[j * n + j];
    for (int k = 0; k < j; ++k) s -= L[j * n + k] * L[j * n + k];
    if (!(s > 0.0)) return 1;
    L[j * n + j] = sqrt(s);
    for (int i = j + 1; i < n; ++i) {
      double t = M[i * n + j];
      for (int k = 0; k < j; ++k) t -= L[i * n + k] * L[j * n + k];
      L[i * n + j] = t / L[j * n + j];
    }
  }
  for (int i = 0; i < n; ++i) {
    double s = x[i];
    for (int k = 0; k < i; ++k) s -= L[i * n + k] * x[k];
    x[i] = s / L[i * n + i];
  }
  for (int i = n - 1; i >= 0; --i) {
    double s = x[i];
    for (int k = i + 1; k < n; ++k) s -= L[k * n + i] * x[k];
    x[i] = s / L[i * n + i];
  }
  return 0;
}

/* The Kalman update with y (UnscentedKalmanFilter.update); the NIS into *nis; 1 if
   degenerate (y not finite, or the innovation covariance not positive definite). */
static int ukf_update(lfm_controller* c, const double* y, double* nis) {
  enum { D = LFM_D, NX = LFM_NX };
  double Sm[NX * NX], L[NX * NX], r[NX], Kt[NX * D], col[NX];
  for (int m = 0; m < NX; ++m)
    if (!isfinite(y[m])) return 1;
  for (int a = 0; a < NX; ++a) {
    r[a] = y[a] - c->mean[a];
    for (int b = 0; b < NX; ++b) Sm[a * NX + b] = c->cov[a * D + b];
    Sm[a * (NX + 1)] += CFG->measurement_std[a] * CFG->measurement_std[a];
  }
  for (int j = 0; j < D; ++j) { /* column j of S^-1 P[:nx, :] = row j of the gain */
    for (int a = 0; a < NX; ++a) col[a] = c->cov[a * D + j];
    if (spd_solve(NX, Sm, L, col)) return 1;
    for (int a = 0; a < NX; ++a) Kt[a * D + j] = col[a];
  }
  for (int j = 0; j < D; ++j) {
    double s = 0.0;
    for (int a = 0; a < NX; ++a) s += Kt[a * D + j] * r[a];
    c->mean[j] += s;
  }
  /* P - K S K' = P - P[:, :nx] S^-1 P[:nx, :] = P - P[:, :nx] Kt */
  double P0[D * NX];
  for (int i = 0; i < D; ++i)
    for (int a = 0; a < NX; ++a) P0[i * NX + a] = c->cov[i * D + a];
  for (int i = 0; i < D; ++i)
    for (int j = 0; j <= i; ++j) {
      double s = 0.0;
      for (int a = 0; a < NX; ++a) s += P0[i * NX + a] * Kt[a * D + j];
      const double v = c->cov[i * D + j] - s;
      c->cov[i * D + j] = v;
      if (j < i) c->cov[j * D + i] = v;
    }
  for (int i = 0; i < D; ++i) /* symmetric: 0.5 (P + P') of the lower triangle written twice */
    for (int j = 0; j < i; ++j) c->cov[j * D + i] = c->cov[i * D + j];
  memcpy(col, r, sizeof(r));
  if (spd_solve(NX, Sm, L, col)) return 1;
  double q = 0.0;
  for (int a = 0; a < NX; ++a) q += r[a] * col[a];
  *nis = q;
  return 0;
}

/* The agent's estimate from y: 0, or 1 if the measurement restarted the estimate. */
static int estimate(lfm_controller* c, const double* y) {
  if (CFG->estimator == LFM_ESTIMATOR_NONE) {
    memset(c->mean, 0, sizeof(c->mean));
    memcpy(c->mean, y, sizeof(double) * LFM_NX);
    memset(c->cov, 0, sizeof(c->cov));
    c->started = 1;
    return 0;
  }
  if (!c->started) {
    ukf_start(c, y);
    return 0;
  }
  double nis = 0.0;
  int degenerate = ukf_predict(c, c->u_prev);
  if (!degenerate) degenerate = ukf_update(c, y, &nis);
  if (degenerate || nis > CFG->divergence_nis) {
    ukf_start(c, y);
    c->info.filter_resets += 1;
    return 1;
  }
  return 0;
}

/* ------------------------------------------------------------------ the scenarios */

/* Latent forces of scenario i from z (P): H z_k for k < N, z_k+1 = A z_k (+ noise). */
static void forecast(lfm_controller* c, long i, const double* z0, int sampled) {
  double z[LFM_NP + 1], zn[LFM_NP + 1];
  memcpy(z, z0, sizeof(double) * LFM_NP);
  for (long k = 0; k < LFM_N; ++k) {
    for (int a = 0; a < LFM_NW; ++a) {
      double w = 0.0;
      for (int b = 0; b < LFM_NP; ++b) w += CFG->H[a * LFM_NP + b] * z[b];
      c->W[(i * LFM_N + k) * LFM_NW + a] = w;
    }
    for (int a = 0; a < LFM_NP; ++a) {
      double s = 0.0;
      for (int b = 0; b < LFM_NP; ++b) s += CFG->A[a * LFM_NP + b] * z[b];
      zn[a] = s;
    }
    if (sampled) {
      double xi[LFM_NP + 1];
      for (int b = 0; b < LFM_NP; ++b) xi[b] = standard_normal(c);
      for (int a = 0; a < LFM_NP; ++a)
        for (int b = 0; b < LFM_NP; ++b) zn[a] += CFG->Q_factor[a * LFM_NP + b] * xi[b];
    }
    memcpy(z, zn, sizeof(double) * LFM_NP);
  }
}

/* x0 and W of the agent (MPCAgent._scenarios); 1 if a factor failed. */
static int scenarios(lfm_controller* c) {
  if (CFG->forecast == LFM_FORECAST_ZERO) {
    for (long i = 0; i < LFM_NS; ++i) memcpy(c->x0 + i * LFM_NX, c->mean, sizeof(double) * LFM_NX);
    memset(c->W, 0, sizeof(c->W));
    return 0;
  }
  if (!CFG->particles || CFG->forecast == LFM_FORECAST_MEAN) {
    for (long i = 0; i < LFM_NS; ++i) {
      memcpy(c->x0 + i * LFM_NX, c->mean, sizeof(double) * LFM_NX);
      forecast(c, i, c->mean + LFM_NX, CFG->forecast == LFM_FORECAST_SAMPLED);
    }
    return 0;
  }
  double S[LFM_D * LFM_D], draw[LFM_D], xi[LFM_D];
  if (psd_factor(c->cov, S)) return 1;
  for (long i = 0; i < LFM_NS; ++i) { /* a draw of [x, z] from the estimate per scenario */
    for (int b = 0; b < LFM_D; ++b) xi[b] = standard_normal(c);
    for (int a = 0; a < LFM_D; ++a) {
      double s = c->mean[a];
      for (int b = 0; b < LFM_D; ++b) s += S[a * LFM_D + b] * xi[b];
      draw[a] = s;
    }
    memcpy(c->x0 + i * LFM_NX, draw, sizeof(double) * LFM_NX);
    forecast(c, i, draw + LFM_NX, 1);
  }
  return 0;
}

/* The back-off k_j sqrt(dg_j' Sigma_x dg_j) at the estimate's mean (_FilteringAgent._backoff),
   the same at every step. */
static int backoff(lfm_controller* c) {
  c->has_backoff = 0;
  if (!CFG->backoff_k || LFM_NG == 0) return 0;
  double J[LFM_NG * LFM_NX + 1];
  if (lfm_constraint_jacobian(c->mean, J)) return 1;
  for (int j = 0; j < LFM_NG; ++j) {
    double s = 0.0;
    for (int a = 0; a < LFM_NX; ++a)
      for (int b = 0; b < LFM_NX; ++b) s += J[j * LFM_NX + a] * c->cov[a * LFM_D + b] * J[j * LFM_NX + b];
    const double v = CFG->backoff_k[j] * sqrt(fmax(s, 0.0));
    for (long k = 0; k < LFM_N; ++k) c->backoff[k * LFM_NG + j] = v;
  }
  c->has_backoff = 1;
  return 0;
}

/* ------------------------------------------------------------------ solves and steps */

/* The API's successes are the solver's (sqp_interface.h). */
typedef char lfm_status_codes_agree[LFM_SOLVED == SQ_SUCCEEDED && LFM_ACCEPTABLE == SQ_ACCEPTABLE
                                        ? 1 : -1];

static int solve(lfm_controller* c, const double* bk) {
  const double t0 = now();
  const int status = lfm_sqp_solve(c->sqp, c->x0, c->W, NULL, bk, c->plan, NULL, c->stats);
#if LFM_FEEDBACK_PREDICTION
  /* a feedback plan: the agent keeps its nominal inputs (the first is v_0, the input applied) */
  if (status != SQ_OUT_OF_MEMORY && isfinite(c->plan[0])) lfm_sqp_law(c->sqp, NULL, NULL, c->plan);
#endif
  c->info.solve_time = now() - t0;
  c->info.status = status;
  c->info.success = status == LFM_SOLVED || status == LFM_ACCEPTABLE;
  /* usable (MPCSolution.usable): converged, or a finite merit below the warm start's */
  c->info.usable = c->info.success ||
                   (isfinite(c->stats[ST_MERIT]) && c->stats[ST_MERIT] < c->stats[ST_START_MERIT]);
  c->info.objective = c->stats[ST_MERIT];
  c->info.slack = c->stats[ST_SLACK];
  c->info.iterations = (long)c->stats[ST_ITERATIONS];
  return status;
}

static int all_finite(const double* a, long n) {
  for (long i = 0; i < n; ++i)
    if (!isfinite(a[i])) return 0;
  return 1;
}

/* No plan (bad input, or no step exported): the fallback input, recorded as such. */
static void no_plan(lfm_controller* c, int status, double* u) {
  c->info.status = status, c->info.success = 0, c->info.usable = 0;
  c->info.action = LFM_FROM_FALLBACK;
  c->plan_at = LFM_N;
  memcpy(u, CFG->fallback_input, sizeof(double) * LFM_NU);
}

int lfm_controller_solve(lfm_controller* c, const double* x0, const double* W, double* plan) {
  if (!all_finite(x0, LFM_NX) || !all_finite(W, (long)LFM_NS * LFM_N * LFM_NW)) {
    for (long k = 0; k < LFM_N; ++k) no_plan(c, LFM_BAD_INPUT, plan + k * LFM_NU);
    return LFM_BAD_INPUT;
  }
  for (long i = 0; i < LFM_NS; ++i) memcpy(c->x0 + i * LFM_NX, x0, sizeof(double) * LFM_NX);
  memcpy(c->W, W, sizeof(c->W));
  c->has_backoff = 0;
  const int status = solve(c, NULL);
  memcpy(plan, c->plan, sizeof(c->plan));
  c->plan_at = c->info.usable ? 0 : LFM_N;
  return status;
}

/* The input after a solve (MPCAgent._choose_action). */
static void choose(lfm_controller* c, double* u, const double* last, long last_at) {
  if (c->info.usable && all_finite(c->plan, LFM_N * LFM_NU)) {
    c->plan_at = 0;
    c->info.action = LFM_FROM_PLAN;
    for (int q = 0; q < LFM_NU; ++q) {
      const double lo = CFG->problem.input_lower[q], hi = CFG->problem.input_upper[q];
      for (long k = 0; k < LFM_N; ++k) {
        double* v = c->plan + k * LFM_NU + q;
        *v = *v < lo ? lo : (*v > hi ? hi : *v);
      }
    }
    memcpy(u, c->plan, sizeof(double) * LFM_NU);
  } else if (last_at + 1 < LFM_N) {
    memcpy(c->plan, last, sizeof(c->plan));
    c->plan_at = last_at + 1;
    c->info.action = LFM_FROM_PREVIOUS_PLAN;
    memcpy(u, c->plan + c->plan_at * LFM_NU, sizeof(double) * LFM_NU);
  } else {
    c->plan_at = LFM_N;
    c->info.action = LFM_FROM_FALLBACK;
    memcpy(u, CFG->fallback_input, sizeof(double) * LFM_NU);
  }
}

int lfm_controller_step(lfm_controller* c, const double* y, double* u) {
  if (CFG->estimator == LFM_ESTIMATOR_OTHER) {
    no_plan(c, LFM_NO_STEP, u);
    return LFM_NO_STEP;
  }
  if (!all_finite(y, LFM_NX)) { /* the fallback input; the estimate moves one step on */
    if (CFG->estimator != LFM_ESTIMATOR_NONE && c->started && ukf_predict(c, c->u_prev))
      c->started = 0; /* (a failed factor: the next measurement starts it again) */
    no_plan(c, LFM_BAD_INPUT, u);
    memcpy(c->u_prev, u, sizeof(c->u_prev));
    return LFM_BAD_INPUT;
  }
  const double t0 = now();
  estimate(c, y);
  double last[LFM_N * LFM_NU];
  const long last_at = c->plan_at;
  memcpy(last, c->plan, sizeof(last));
  int status;
  if (scenarios(c) || backoff(c)) {
    status = LFM_OUT_OF_MEMORY; /* (a factor failed: no plan) */
    c->info.status = status, c->info.success = 0, c->info.usable = 0;
  } else {
    status = solve(c, c->has_backoff ? c->backoff : NULL);
  }
  choose(c, u, last, last_at);
  memcpy(c->u_prev, u, sizeof(c->u_prev));
  c->info.step_time = now() - t0;
  return status;
}

void lfm_controller_last_problem(const lfm_controller* c, double* x0, double* W, double* bk) {
  if (x0) memcpy(x0, c->x0, sizeof(c->x0));
  if (W) memcpy(W, c->W, sizeof(c->W));
  if (bk) {
    if (c->has_backoff)
      memcpy(bk, c->backoff, sizeof(double) * LFM_N * LFM_NG);
    else
      memset(bk, 0, sizeof(double) * LFM_N * LFM_NG);
  }
}

void lfm_controller_estimate(const lfm_controller* c, double* mean, double* cov) {
  if (mean) memcpy(mean, c->mean, sizeof(c->mean));
  if (cov) memcpy(cov, c->cov, sizeof(c->cov));
}

lfm_info lfm_controller_info(const lfm_controller* c) { return c->info; }

const char* lfm_status_name(int status) {
  static const char* names[] = LFM_SQP_STATUS_NAMES; /* sqp_interface.h */
  if (status >= 0 && status < (int)(sizeof(names) / sizeof(names[0]))) return names[status];
  if (status == LFM_NO_STEP) return "No_Step_Exported";
  if (status == LFM_BAD_INPUT) return "Bad_Input";
  if (status == LFM_OUT_OF_MEMORY) return "Out_Of_Memory";
  return "Unknown";
}
