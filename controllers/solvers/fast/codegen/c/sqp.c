/* The fast SQP's loop in C: one call per solve (lfm_sqp_solve).

   The same algorithm as the Python loop it is checked against (controllers/solvers/fast/
   solver.py, subproblem.py, globalisation.py, restarts.py: read those for the why of every
   step): per iteration the linearisation and the exact Hessian of the C library's driver
   (driver.c, hessian.c), the convexification (a Cholesky test, else an eigen-decomposition
   and sigma J_A' J_A of the constraints predicted active, else the eigenvalue floor), the
   screened scenario rows (selection.c) with check-and-add over every row, the QP without
   slacks first (elastic_qp="on_demand") with its multiplier test, else the elastic QP, the
   box trust region, the backtracking line search on the exact-penalty merit with the
   second-order correction and the expansion of good full steps, the stopping tests, and the
   extra starts of mirror-symmetric inputs. The QPs are solved by the project's own C: the
   elastic interior point (elastic_ipm.c) for the QPs with slacks, a dual active-set method
   (dense.c) for those without. Where the Python loop calls NumPy the sums here are the same
   sums, in NumPy's order where that is cheap to keep (its pairwise summation); BLAS dot
   products and LAPACK factorisations differ from these by rounding.

   Appended to the system's generated library (build.library_source); this file includes
   the QP solvers. Entry points: lfm_sqp_new, lfm_sqp_solve, lfm_sqp_reset, lfm_sqp_free. */
#include <float.h>
#include <time.h>

#include "sqp.h"

#include "elastic_ipm.c"

#include "dense.c"

/* The statuses SQ_* and the statistics ST_* are sqp_interface.h's (codegen/interface.py). */
#define SQ_NONE (-1) /* no status yet: the start goes on */
#define SQ_OUT_OF_TIME (-2) /* inside an iteration (the Python loop's _OutOfTime) */

typedef struct {
  double *u, *X, *G;   /* (N NU), (N + 1, NX, Ns), (NGR, N, Ns) */
  double slack, merit; /* sum of the minimal slacks; exact-penalty merit (inf if not finite) */
  int used;
} ro_t;

#define SQ_POOL 8

typedef struct {
  long r, cap;
  long* pos; /* (r, 3) scenario rows (constraint, step from 0, scenario) */
  double *a, *g; /* (r, N NU) their Jacobian rows, (r) their values */
} rows_t;

struct lfm_sqp {
  long n, ns, nut, nL, nsh, nsc, n_groups, nmirror;
  lfm_sqp_options o;
  double rho;
  double *lower, *upper, *range, *goal, *Wq, *Q0, *R, *R2, *r_diag, *a_shared;
  long *shared, *screened, *mirror;
  unsigned char* depends;
  int diagonal, q_diagonal;
  /* one solve's data */
  double *x0T, *W, *backoff, cost0;
  int has_backoff;
  double deadline;
  ro_t pool[SQ_POOL];
  /* the linearisation, Hessians and multipliers */
  double *S, *Jg, *grad, *H, *Hq, *Hw, *Hw2, *Hw3, *eig_w, *eig_V, *scratch, *mu, *mu_next;
  /* the QP */
  rows_t scr, rows, act;   /* screened rows, the QP's rows, the rows predicted active */
  long *act_shared, n_act_shared, *bounds, n_bounds;
  long *missing, missing_cap, *groups, *col;
  double *lo, *hi, *gsh, *qA, *qb, *qrho, *qreg, *qd, *qs, *qlam, *qz_sum, *sigJ;
  long qm; /* rows of the last QP (shared first) */
  long qG; /* its slack columns */
  long q_groups_cap;
  int q_hard;
  /* the step of the last QP */
  double *d, *s_pos, *s_shared, *lam_shared, *lam_pos, slack_sum, curvature;
  /* per start */
  double radius;
  int hard_first;
  double stats[ST_COUNT];
  double *prev_u;
  int has_prev;
  double *u_try, *u_prev;
  /* a feedback prediction (LFM_FEEDBACK; feedback.c): the data rows the driver reads as its
     inputs (N, ND), the law (N, NU, NX), (N, NX), the bounds of v in the two kinds of solve
     (every v_k, or v_0 only), the reference plan (the nominal inputs of the last usable
     plan), the last decision and open-loop plan, the nominal inputs of the last solve */
  double *D, *law_K, *law_r, *lower_all, *upper_all, *lower_first, *upper_first;
  double *ref_plan, *last_v, *last_open, *nominal, *fb_work;
  int law_given, has_ref, has_last_v, has_last_open;
};

#ifdef LFM_FEEDBACK
static long fb_work_size(long n); /* (feedback.c) */
#endif
/* The timed parts (their definitions below, "where the time goes"). */
static ro_t* sq_evaluate(lfm_sqp* s, const double* u);
static int sq_linearise(lfm_sqp* s, const ro_t* ro);
static void sq_hessian(lfm_sqp* s, const ro_t* ro);
static void sq_rows(lfm_sqp* s, const ro_t* ro, rows_t* r, long from);
static double sq_convexify(lfm_sqp* s, const ro_t* ro);
static int sq_solve_elastic(lfm_sqp* s);
static int sq_solve_hard(lfm_sqp* s);

/* What the driver reads as the inputs u (N NU): u itself, or with feedback the law's data
   rows with u as the nominal inputs. */
static const double* sq_data(lfm_sqp* s, const double* u) {
#ifdef LFM_FEEDBACK
  for (long k = 0; k < s->n; ++k) memcpy(s->D + k * ND, u + k * NU, sizeof(double) * NU);
  return s->D;
#else
  (void)s;
  return u;
#endif
}

static double sq_now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* NumPy's sum of a[0..n) (its pairwise summation: blocks of 8 accumulators up to 128 values,
   halves above), so that slacks and means round as in the Python loop. */
static double np_sum(const double* a, long n) {
  if (n < 8) {
    double r = 0.0; /* (NumPy adds -0.0 first; the same for every finite sum but -0.0) */
    for (long i = 0; i < n; ++i) r += a[i];
    return r;
  }
  if (n <= 128) {
    double r[8];
    long i;
    for (int j = 0; j < 8; ++j) r[j] = a[j];
    for (i = 8; i < n - (n % 8); i += 8)
      for (int j = 0; j < 8; ++j) r[j] += a[i + j];
    double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
    for (; i < n; ++i) res += a[i];
    return res;
  }
  long n2 = n / 2;
  n2 -= n2 % 8;
  return np_sum(a, n2) + np_sum(a + n2, n - n2);
}

/* The largest of g[0..ns) (NaN if any is NaN, as np.max). */
static double np_max(const double* g, long ns) {
  double m = g[0];
  int nan = m != m;
  for (long i = 1; i < ns; ++i) {
    nan |= g[i] != g[i];
    if (g[i] > m) m = g[i];
  }
  return nan ? NAN : m;
}

static void* sq_alloc(size_t count, size_t size, int* fail) {
  void* p = calloc(count ? count : 1, size);
  if (!p) *fail = 1;
  return p;
}

static int rows_reserve(rows_t* r, long cap, long nut) {
  if (cap <= r->cap) return 0;
  long c = r->cap ? r->cap : 16;
  while (c < cap) c *= 2;
  long* pos = realloc(r->pos, sizeof(long) * 3 * c);
  if (pos) r->pos = pos;
  double* a = realloc(r->a, sizeof(double) * c * (nut ? nut : 1));
  if (a) r->a = a;
  double* g = realloc(r->g, sizeof(double) * c);
  if (g) r->g = g;
  if (!pos || !a || !g) return 1;
  r->cap = c;
  return 0;
}

static void rows_free(rows_t* r) {
  free(r->pos);
  free(r->a);
  free(r->g);
}

CASADI_SYMBOL_EXPORT void lfm_sqp_free(lfm_sqp* s) {
  if (!s) return;
  void* own[] = {s->D, s->law_K, s->law_r, s->lower_all, s->upper_all, s->lower_first,
                 s->upper_first, s->ref_plan, s->last_v, s->last_open, s->nominal, s->fb_work,
                 s->range, s->goal, s->Wq, s->Q0, s->R, s->R2, s->r_diag,
                 s->a_shared, s->shared, s->screened, s->mirror, s->depends, s->x0T, s->W,
                 s->backoff, s->S, s->Jg, s->grad, s->H, s->Hq, s->Hw, s->Hw2, s->Hw3, s->eig_w,
                 s->eig_V, s->scratch, s->mu, s->mu_next, s->act_shared, s->bounds, s->missing,
                 s->groups, s->col, s->lo, s->hi, s->gsh, s->qA, s->qb, s->qrho, s->qreg, s->qd,
                 s->qs, s->qlam, s->qz_sum, s->sigJ, s->d, s->s_pos, s->s_shared,
                 s->lam_shared, s->lam_pos, s->prev_u, s->u_try, s->u_prev};
  for (size_t i = 0; i < sizeof(own) / sizeof(own[0]); ++i) free(own[i]);
  for (int i = 0; i < SQ_POOL; ++i) {
    free(s->pool[i].u);
    free(s->pool[i].X);
    free(s->pool[i].G);
  }
  rows_free(&s->scr);
  rows_free(&s->rows);
  rows_free(&s->act);
  free(s);
}

/* The QP arrays for m scenario rows (and G slack columns) at most. */
static int sq_reserve_qp(lfm_sqp* s, long r) {
  const long nut = s->nut, m = s->nsh + r;
  if (rows_reserve(&s->rows, r, nut)) return 1;
  if (r <= s->q_groups_cap) return 0;
  long c = s->q_groups_cap ? s->q_groups_cap : 16;
  while (c < r) c *= 2;
  const long mc = s->nsh + c;
  double* p;
  long* l;
#define GROW(field, type, count)                                  \
  if (!(p = realloc(s->field, sizeof(type) * (count)))) return 1; \
  s->field = (type*)p;
#define GROWL(field, count)                                   \
  if (!(l = realloc(s->field, sizeof(long) * (count)))) return 1; \
  s->field = l;
  GROW(qA, double, mc * nut)
  GROW(qb, double, mc)
  GROW(qrho, double, mc)
  GROW(qreg, double, mc)
  GROW(qs, double, mc)
  GROW(qlam, double, mc)
  GROW(lam_pos, double, c)
  GROWL(groups, c)
  GROWL(col, mc)
#undef GROW
#undef GROWL
  (void)m;
  s->q_groups_cap = c;
  return 0;
}

CASADI_SYMBOL_EXPORT lfm_sqp* lfm_sqp_new(const lfm_sqp_problem* p, const lfm_sqp_options* o) {
  lfm_sqp* s = calloc(1, sizeof(lfm_sqp));
  if (!s) return NULL;
  s->hard_first = 1;
  int fail = 0;
  const long n = p->n, ns = p->ns, nut = n * NU, nL = p->n_shared;
  s->n = n, s->ns = ns, s->nut = nut, s->nL = nL, s->nsh = nL * n, s->nsc = p->n_screened;
  s->n_groups = p->n_screened * n > 1 ? p->n_screened * n : 1;
  s->nmirror = p->n_mirror;
  s->o = *o;
  s->rho = p->slack_penalty;
#define ALLOC(type, count) (type*)sq_alloc((size_t)(count), sizeof(type), &fail)
  s->lower = s->lower_all = ALLOC(double, nut);
  s->upper = s->upper_all = ALLOC(double, nut);
  s->lower_first = ALLOC(double, nut);
  s->upper_first = ALLOC(double, nut);
  s->range = ALLOC(double, nut);
  for (long k = 0; k < n && !fail; ++k)
    for (int q = 0; q < NU; ++q) {
      const long i = k * NU + q;
      s->lower[i] = p->input_lower[q];
      s->upper[i] = p->input_upper[q];
      s->lower_first[i] = k ? -INFINITY : p->input_lower[q]; /* (feedback: v_0 bounded) */
      s->upper_first[i] = k ? INFINITY : p->input_upper[q];
      const double span = s->upper[i] - s->lower[i];
      s->range[i] = isfinite(span) && span > 0.0 ? span : INFINITY;
    }
  s->goal = ALLOC(double, NX);
  s->Wq = ALLOC(double, n * NX * NX);
  s->Q0 = ALLOC(double, NX * NX);
  s->R = ALLOC(double, NU * NU);
  s->R2 = ALLOC(double, NU * NU);
  s->r_diag = ALLOC(double, nut);
  if (!fail) {
    memcpy(s->goal, p->goal, sizeof(double) * NX);
    memcpy(s->Q0, p->Q, sizeof(double) * NX * NX);
    for (long k = 0; k < n; ++k)
      memcpy(s->Wq + k * NX * NX, k + 1 < n ? p->Q : p->Qf, sizeof(double) * NX * NX);
    memcpy(s->R, p->R, sizeof(double) * NU * NU);
    for (int e = 0; e < NU * NU; ++e) s->R2[e] = 2.0 * p->R[e];
    for (long i = 0; i < nut; ++i) s->r_diag[i] = p->R[(i % NU) * (NU + 1)];
    int diag = 1, qdiag = 1;
    for (int a = 0; a < NX; ++a)
      for (int b = 0; b < NX; ++b)
        if (a != b) {
          qdiag &= p->Q[a * NX + b] == 0.0;
          diag &= p->Q[a * NX + b] == 0.0 && p->Qf[a * NX + b] == 0.0;
        }
    for (int a = 0; a < NU; ++a)
      for (int b = 0; b < NU; ++b)
        if (a != b) diag &= p->R[a * NU + b] == 0.0;
    s->diagonal = diag, s->q_diagonal = qdiag;
  }
  s->shared = ALLOC(long, nL + 1);
  s->a_shared = ALLOC(double, s->nsh * nut + 1);
  s->screened = ALLOC(long, s->nsc + 1);
  s->mirror = ALLOC(long, s->nmirror + 1);
  s->depends = ALLOC(unsigned char, NGR * NX + 1);
  if (!fail) {
    memcpy(s->shared, p->shared, sizeof(long) * nL);
    for (long k = 0; k < n; ++k) /* ordered (step, shared constraint) */
      for (long l = 0; l < nL; ++l)
        memcpy(s->a_shared + (k * nL + l) * nut, p->shared_rows + (l * n + k) * nut,
               sizeof(double) * nut);
    memcpy(s->screened, p->screened, sizeof(long) * s->nsc);
    memcpy(s->mirror, p->mirror, sizeof(long) * s->nmirror);
    memcpy(s->depends, p->depends, NGR * NX);
  }
  s->x0T = ALLOC(double, NX * ns);
  s->W = ALLOC(double, NW * n * ns);
  s->backoff = ALLOC(double, NG * n + 1);
  for (int i = 0; i < SQ_POOL; ++i) {
    s->pool[i].u = ALLOC(double, nut);
    s->pool[i].X = ALLOC(double, (n + 1) * NX * ns);
    s->pool[i].G = ALLOC(double, NGR * n * ns + 1);
  }
  s->S = ALLOC(double, ns * NXS * NU * n * (n + 1) / 2);
  s->Jg = ALLOC(double, n * ns * GR_NNZ + 1);
#ifdef LFM_FEEDBACK
  s->D = ALLOC(double, n * ND);
  s->law_K = ALLOC(double, n * NU * NX);
  s->law_r = ALLOC(double, n * NX);
  s->ref_plan = ALLOC(double, nut);
  s->last_v = ALLOC(double, nut);
  s->last_open = ALLOC(double, nut);
  s->nominal = ALLOC(double, nut);
  s->fb_work = ALLOC(double, fb_work_size(n));
  if (!fail)
    for (long k = 0; k < n; ++k) /* the input weight of every data row */
      memcpy(s->D + k * ND + NDF, p->R, sizeof(double) * NU * NU);
#endif
  s->grad = ALLOC(double, nut);
  s->H = ALLOC(double, nut * nut);
  s->Hq = ALLOC(double, nut * nut);
  s->Hw = ALLOC(double, nut * nut);
  s->Hw2 = ALLOC(double, nut * nut + 3 * nut);
  s->Hw3 = ALLOC(double, nut * nut);
  s->eig_w = ALLOC(double, nut);
  s->eig_V = ALLOC(double, nut * nut);
  s->scratch = ALLOC(double, lfm_hessian_scratch(ns));
  s->mu = ALLOC(double, NGR * n * ns + 1);
  s->mu_next = ALLOC(double, NGR * n * ns + 1);
  s->act_shared = ALLOC(long, s->nsh + 1);
  s->bounds = ALLOC(long, nut);
  s->lo = ALLOC(double, nut);
  s->hi = ALLOC(double, nut);
  s->gsh = ALLOC(double, s->nsh + 1);
  s->qd = ALLOC(double, nut);
  s->d = ALLOC(double, nut);
  s->s_pos = ALLOC(double, NGR * n + 1);
  s->s_shared = ALLOC(double, s->nsh + 1);
  s->lam_shared = ALLOC(double, s->nsh + 1);
  s->prev_u = ALLOC(double, nut);
  s->u_try = ALLOC(double, nut);
  s->u_prev = ALLOC(double, nut);
  s->qz_sum = ALLOC(double, s->nsh + s->n_groups + 8);
  s->missing_cap = s->nsc * n * (ns < o->screen_rows ? ns : o->screen_rows) + 1;
  s->missing = ALLOC(long, 3 * s->missing_cap);
#undef ALLOC
  if (fail || sq_reserve_qp(s, 64)) {
    lfm_sqp_free(s);
    return NULL;
  }
  return s;
}

CASADI_SYMBOL_EXPORT void lfm_sqp_reset(lfm_sqp* s) {
  s->has_prev = 0;
  s->hard_first = 1;
  s->has_ref = s->has_last_v = s->has_last_open = s->law_given = 0;
}

/* The wall-clock limit [s] of the next solves (options.max_time; INFINITY: none). */
CASADI_SYMBOL_EXPORT void lfm_sqp_set_max_time(lfm_sqp* s, double max_time) {
  s->o.max_time = max_time;
}

/* ------------------------------------------------------------------ rollouts */

static ro_t* ro_take(lfm_sqp* s) {
  for (int i = 0; i < SQ_POOL; ++i)
    if (!s->pool[i].used) {
      s->pool[i].used = 1;
      return s->pool + i;
    }
  return NULL;
}

static void ro_give(ro_t* ro) {
  if (ro) ro->used = 0;
}

/* u' R u (CondensedModel.input_cost). */
static double sq_input_cost(const lfm_sqp* s, const double* u) {
  double c = 0.0;
  if (s->diagonal) {
    for (long i = 0; i < s->nut; ++i) c += s->r_diag[i] * (u[i] * u[i]);
    return c;
  }
  for (long k = 0; k < s->n; ++k)
    for (int a = 0; a < NU; ++a)
      for (int b = 0; b < NU; ++b) c += u[k * NU + a] * s->R[a * NU + b] * u[k * NU + b];
  return c;
}

/* The rollout of all scenarios under u and its merit (CondensedModel.evaluate) into a
   rollout of the pool; NULL if the pool is empty. */
static ro_t* sq_evaluate_(lfm_sqp* s, const double* u) {
  ro_t* ro = ro_take(s);
  if (!ro) return NULL;
  const long n = s->n, ns = s->ns;
  memcpy(ro->u, u, sizeof(double) * s->nut);
  double csum = 0.0;
  if (lfm_rollout(n, ns, s->x0T, s->W, n * ns, ns, 1, sq_data(s, ro->u), s->goal, s->Wq, ro->X,
                  ro->G,
                  &csum, s->o.threads)) {
    for (long e = 0; e < (n + 1) * NX * ns; ++e) ro->X[e] = NAN;
    for (long e = 0; e < NGR * n * ns; ++e) ro->G[e] = NAN;
    csum = NAN;
  }
  double slack = 0.0;
  if (NGR) {
    double mx[NGR * n + 1];
    for (long jk = 0; jk < NGR * n; ++jk) {
      double* g = ro->G + jk * ns;
      if (s->has_backoff && jk < NG * n) /* (the state constraints') */
        for (long i = 0; i < ns; ++i) g[i] += s->backoff[jk];
      const double m = np_max(g, ns);
      mx[jk] = m != m ? NAN : (m > 0.0 ? m : 0.0);
    }
    slack = np_sum(mx, NGR * n);
  }
#ifdef LFM_FEEDBACK
  const double inputs = 0.0; /* (each scenario's input cost is in csum) */
#else
  const double inputs = sq_input_cost(s, u);
#endif
  double merit = s->cost0 + csum / (double)ns + inputs + s->rho * slack;
  ro->slack = slack;
  ro->merit = isfinite(merit) ? merit : INFINITY;
  return ro;
}

/* ------------------------------------------------------------------ linearisation */

static int sq_linearise_(lfm_sqp* s, const ro_t* ro) {
  const long n = s->n, ns = s->ns;
  if (lfm_linearise(n, ns, ro->X, s->W, n * ns, ns, 1, sq_data(s, ro->u), s->goal, s->Wq,
                    2.0 / ns, s->S, s->Jg, s->grad, s->o.threads))
    for (long i = 0; i < s->nut; ++i) s->grad[i] = NAN;
#ifdef LFM_FEEDBACK
  return 0; /* (each scenario's input cost is in grad) */
#endif
  for (long k = 0; k < n; ++k)
    for (int q = 0; q < NU; ++q) {
      double t = 0.0;
      for (int a = 0; a < NU; ++a) t += ro->u[k * NU + a] * s->R2[a * NU + q];
      s->grad[k * NU + q] += t;
    }
  return 0;
}

static void sq_hessian_(lfm_sqp* s, const ro_t* ro) {
  const long n = s->n, ns = s->ns, nut = s->nut;
  int any = 0;
  for (long e = 0; e < NGR * n * ns && !any; ++e) any = s->mu[e] != 0.0;
  if (lfm_hessian(n, ns, ro->X, s->W, n * ns, ns, 1, sq_data(s, ro->u), s->S, s->Jg,
                  any ? s->mu : NULL,
                  s->goal, s->Wq, 2.0 / ns, s->H, s->scratch, s->o.threads))
    for (long e = 0; e < nut * nut; ++e) s->H[e] = NAN;
  for (long k = 0; k < n; ++k)
    for (int p = 0; p < NU; ++p)
      for (int q = 0; q < NU; ++q) s->H[(k * NU + p) * nut + k * NU + q] += s->R2[p * NU + q];
}

/* The Jacobian rows and values of rows r->pos[from..r->r) (CondensedModel.rows). */
static void sq_rows_(lfm_sqp* s, const ro_t* ro, rows_t* r, long from) {
  const long q = r->r - from;
  if (q <= 0) return;
  lfm_rows(s->n, s->ns, s->S, s->Jg, q, r->pos + 3 * from, r->a + from * s->nut);
  for (long e = from; e < r->r; ++e) {
    const long* p = r->pos + 3 * e;
    r->g[e] = ro->G[(p[0] * s->n + p[1]) * s->ns + p[2]];
  }
}

/* ------------------------------------------------------------------ convexification */

/* H (or a matrix beside it) made positive definite (SubproblemMixin._convexify) into
   s->Hq; returns sigma (0: no augmentation), -1 when the eigen-decomposition failed. The
   Jacobian rows of the predicted active scenario rows (s->act) are filled when there are
   any. */
static double sq_convexify_(lfm_sqp* s, const ro_t* ro) {
  const long nut = s->nut;
  const double floor = s->o.hessian_floor;
  double *H = s->H, *w = s->eig_w, *V = s->eig_V, *M = s->Hw, *work = s->Hw2;
  for (long e = 0; e < nut * nut; ++e) M[e] = H[e];
  for (long i = 0; i < nut; ++i) M[i * nut + i] -= floor;
  if (dq_positive_definite(nut, M, work)) {
    memcpy(s->Hq, H, sizeof(double) * nut * nut);
    return 0.0;
  }
  if (dq_eigh(nut, H, w, V, work)) return -1.0;
  if (w[0] >= floor) {
    memcpy(s->Hq, H, sizeof(double) * nut * nut);
    return 0.0;
  }
  if (s->act.r) sq_rows(s, ro, &s->act, 0);
  const long nrows = s->act.r + s->n_act_shared + s->n_bounds;
  long below = 0;
  for (long i = 0; i < nut; ++i) below += w[i] < floor;
  const int augmented = s->o.hessian_modification == 2;
  if (nrows && (augmented || nrows >= below)) {
    double* G = s->Hw; /* J'J of the rows */
    memset(G, 0, sizeof(double) * nut * nut);
    for (long e = 0; e < s->act.r; ++e) {
      const double* a = s->act.a + e * nut;
      for (long i = 0; i < nut; ++i)
        for (long j = 0; j < nut; ++j) G[i * nut + j] += a[i] * a[j];
    }
    for (long e = 0; e < s->n_act_shared; ++e) {
      const double* a = s->a_shared + s->act_shared[e] * nut;
      for (long i = 0; i < nut; ++i)
        for (long j = 0; j < nut; ++j) G[i * nut + j] += a[i] * a[j];
    }
    for (long e = 0; e < s->n_bounds; ++e) G[s->bounds[e] * (nut + 1)] += 1.0;
    double wmax = 0.0, gmax = -INFINITY;
    for (long i = 0; i < nut; ++i) {
      wmax = fmax(wmax, fabs(w[i]));
      gmax = fmax(gmax, G[i * (nut + 1)]);
    }
    double sigma = wmax / fmax(gmax, 1e-12);
    for (int attempt = 0; attempt < 4; ++attempt) {
      for (long e = 0; e < nut * nut; ++e) s->Hq[e] = H[e] + sigma * G[e];
      for (long e = 0; e < nut * nut; ++e) s->Hw3[e] = s->Hq[e];
      for (long i = 0; i < nut; ++i) s->Hw3[i * (nut + 1)] -= floor;
      if (dq_positive_definite(nut, s->Hw3, work)) return sigma;
      if (augmented) {
        if (dq_eigh(nut, s->Hq, w, V, work)) return -1.0;
        dq_rebuild(nut, w, V, floor, 0, s->Hq);
        return sigma;
      }
      sigma *= 10.0;
    }
  }
  dq_rebuild(nut, w, V, floor, s->o.hessian_modification == 1, s->Hq);
  return 0.0;
}

/* ------------------------------------------------------------------ the QP */

/* Rank of group id v among the sorted unique ids u (c of them). */
static long sq_rank(const long* u, long c, long v) {
  long a = 0, b = c;
  while (a < b) {
    const long m = (a + b) / 2;
    if (u[m] < v) a = m + 1;
    else b = m;
  }
  return a;
}

/* The QP of the current rows into s->qA, qb (shared rows first): with bpos (or the rows'
   own -g) as the scenario rows' bounds. */
static void sq_load(lfm_sqp* s, const double* bpos) {
  const long nut = s->nut, nsh = s->nsh, r = s->rows.r;
  memcpy(s->qA, s->a_shared, sizeof(double) * nsh * nut);
  memcpy(s->qA + nsh * nut, s->rows.a, sizeof(double) * r * nut);
  for (long i = 0; i < nsh; ++i) s->qb[i] = -s->gsh[i];
  for (long e = 0; e < r; ++e) s->qb[nsh + e] = bpos ? bpos[e] : -s->rows.g[e];
  s->qm = nsh + r;
}

/* The elastic QP of the loaded rows (SlotQP._solve_elastic_ipm; a failure retried with a
   proximal term on the step, as SlotQP.solve retries, but by the same interior point):
   the step into qd, the slacks into qs (qG), the multipliers into qlam; 1 if solved. */
static int sq_solve_elastic_(lfm_sqp* s) {
  const long nut = s->nut, nsh = s->nsh, r = s->rows.r, n = s->n;
  long ng = 0;
  for (long e = 0; e < r; ++e) s->groups[e] = s->rows.pos[3 * e] * n + s->rows.pos[3 * e + 1];
  /* the groups' ids, sorted and unique, in s->col after the shared rows' (scratch) */
  long* uniq = s->col + nsh;
  for (long e = 0; e < r; ++e) uniq[e] = s->groups[e];
  ng = r ? sorted_unique(uniq, r) : 0;
  long ranks[r + 1];
  for (long e = 0; e < r; ++e) ranks[e] = sq_rank(uniq, ng, s->groups[e]);
  for (long i = 0; i < nsh; ++i) s->col[i] = i;
  for (long e = 0; e < r; ++e) s->col[nsh + e] = nsh + ranks[e];
  s->qG = nsh + ng;
  for (long c = 0; c < s->qG; ++c) s->qrho[c] = s->rho, s->qreg[c] = s->o.slack_regularisation;
  long it = 0;
  int code = lfm_elastic_qp(nut, s->qm, s->qG, s->Hq, s->grad, s->lo, s->hi, s->qA, s->qb,
                            s->col, s->qrho, s->qreg, 1e-9, 1e-12, 1e-12, 0.995, 100, s->qd,
                            s->qs, s->qlam, &it);
  s->stats[ST_QP_ELASTIC] += 1;
  s->stats[ST_QP_IPM_ITERATIONS] += (double)it;
  if (code == 0) return 1;
  s->stats[ST_QP_RETRIES] += 1;
  double scale = 1.0;
  for (long i = 0; i < nut; ++i) scale = fmax(scale, fabs(s->Hq[i * (nut + 1)]));
  static const double prox[] = {1e-8, 1e-4};
  for (int a = 0; a < 2 && code; ++a) {
    memcpy(s->Hw, s->Hq, sizeof(double) * nut * nut);
    for (long i = 0; i < nut; ++i) s->Hw[i * (nut + 1)] += prox[a] * scale;
    code = lfm_elastic_qp(nut, s->qm, s->qG, s->Hw, s->grad, s->lo, s->hi, s->qA, s->qb, s->col,
                          s->qrho, s->qreg, 1e-9, 1e-12, 1e-12, 0.995, 100, s->qd, s->qs,
                          s->qlam, &it);
  }
  return code == 0;
}

/* The QP without slacks of the loaded rows: the step into qd, multipliers into qlam. */
static int sq_solve_hard_(lfm_sqp* s) {
  long steps = 0;
  const int code = lfm_dense_qp(s->nut, s->qm, s->Hq, s->grad, s->lo, s->hi, s->qA, s->qb,
                                1e-10, 50 * (s->nut + s->qm) + 100, s->qd, s->qlam, &steps);
  return code == DQ_SOLVED;
}

/* The slacks of the last elastic QP summed as the Python loop sums z[nu:] (NumPy, over the
   shared slacks and every group column of its QP object, the unused ones zero). */
static double sq_slack_sum(lfm_sqp* s, long n_groups_used) {
  const long nsh = s->nsh;
  long cap = 1;
  const long want = n_groups_used > 1 ? n_groups_used : 1;
  while (cap < want) cap <<= 1;
  if (cap < 4) cap = 4;
  if (cap > s->n_groups) cap = s->n_groups;
  const long len = nsh + cap;
  double* z = s->qz_sum;
  memset(z, 0, sizeof(double) * len);
  for (long c = 0; c < s->qG; ++c) z[c] = s->qs[c];
  return np_sum(z, len);
}

/* The step of the full QP by check-and-add (SubproblemMixin._solve_qp) from the screened
   rows, with Hessian s->Hq at the iterate ro: 1 solved, 0 failed, SQ_OUT_OF_TIME. */
static int sq_solve_qp(lfm_sqp* s, const ro_t* ro) {
  const long nut = s->nut, nsh = s->nsh, n = s->n;
  int hard = s->hard_first;
  for (long i = 0; i < nut; ++i) {
    double lo = s->lower[i] - ro->u[i], hi = s->upper[i] - ro->u[i];
    if (s->radius > 0.0) {
      lo = fmax(lo, -s->radius * s->range[i]);
      hi = fmin(hi, s->radius * s->range[i]);
    }
    s->lo[i] = lo, s->hi[i] = hi;
  }
  if (sq_reserve_qp(s, s->scr.r)) return 0;
  s->rows.r = s->scr.r;
  memcpy(s->rows.pos, s->scr.pos, sizeof(long) * 3 * s->scr.r);
  sq_rows(s, ro, &s->rows, 0);
  for (long round = 0; round < s->o.max_qp_rounds; ++round) {
    if (sq_now() >= s->deadline) return SQ_OUT_OF_TIME;
    const long r = s->rows.r;
    memset(s->s_pos, 0, sizeof(double) * NGR * n);
    sq_load(s, NULL);
    if (hard) {
      int ok = sq_solve_hard(s);
      s->stats[ST_QP_SOLVES] += 1, s->stats[ST_QP_HARD] += 1;
      for (long i = 0; i < nsh && ok; ++i) ok = s->qlam[i] <= s->rho;
      if (ok && r) { /* each group's multipliers summed (np.bincount), the largest <= rho */
        double sums[NGR * n + 1];
        memset(sums, 0, sizeof(double) * (NGR * n + 1));
        for (long e = 0; e < r; ++e)
          sums[s->rows.pos[3 * e] * n + s->rows.pos[3 * e + 1]] += s->qlam[nsh + e];
        double mx = 0.0;
        for (long g = 0; g < NGR * n; ++g) mx = fmax(mx, sums[g]);
        ok = mx <= s->rho;
      }
      if (ok) {
        s->slack_sum = 0.0;
        memset(s->s_shared, 0, sizeof(double) * nsh);
        s->q_hard = 1;
      } else {
        hard = 0;
        s->stats[ST_QP_HARD_REJECTED] += 1;
      }
    }
    if (!hard) {
      const int ok = sq_solve_elastic(s);
      s->stats[ST_QP_SOLVES] += 1;
      if (!ok) return 0;
      s->q_hard = 0;
      for (long e = 0; e < r; ++e) s->s_pos[s->groups[e]] = s->qs[s->col[nsh + e]];
      memcpy(s->s_shared, s->qs, sizeof(double) * nsh);
      s->slack_sum = sq_slack_sum(s, s->qG - nsh);
    }
    const double t_rows = sq_now();
    const long got = lfm_violated(n, s->ns, s->nsc, s->screened, s->S, s->Jg, ro->G, s->qd,
                                  s->s_pos, r, s->rows.pos, s->o.add_tol, s->o.screen_rows,
                                  s->missing, s->missing_cap);
    s->stats[ST_TIME_ROWS] += sq_now() - t_rows;
    if (got < 0) return 0;
    if (got == 0) break;
    if (round == s->o.max_qp_rounds - 1) {
      s->stats[ST_QP_ROUNDS_EXHAUSTED] += 1;
      break;
    }
    if (sq_reserve_qp(s, r + got)) return 0;
    memcpy(s->rows.pos + 3 * r, s->missing, sizeof(long) * 3 * got);
    s->rows.r = r + got;
    sq_rows(s, ro, &s->rows, r);
  }
  if (s->rows.r > s->stats[ST_QP_ROWS]) s->stats[ST_QP_ROWS] = (double)s->rows.r;
  memcpy(s->d, s->qd, sizeof(double) * nut);
  for (long i = 0; i < nsh; ++i) s->lam_shared[i] = fmax(s->qlam[i], 0.0);
  for (long e = 0; e < s->rows.r; ++e) s->lam_pos[e] = fmax(s->qlam[nsh + e], 0.0);
  return 1;
}

static int sq_is_bound(const lfm_sqp* s, const double* u, long i) {
  return u[i] <= s->lower[i] + 1e-12 || u[i] >= s->upper[i] - 1e-12;
}

/* The QP step with a convexified Hessian (SubproblemMixin._newton_step) from ro; the
   scenario rows' multipliers into s->mu_next. 1 solved, or a status (negated) when the
   start ends: -SQ_QP_FAILED, -SQ_NUMERICAL_ERROR, SQ_OUT_OF_TIME. */
static int sq_newton_step(lfm_sqp* s, const ro_t* ro, double damping) {
  const long nut = s->nut, n = s->n, ns = s->ns, nsh = s->nsh;
  const double* u = ro->u;
  s->n_bounds = 0;
  for (long i = 0; i < nut; ++i)
    if (sq_is_bound(s, u, i)) s->bounds[s->n_bounds++] = i;
  /* the screened rows */
  s->scr.r = 0;
  if (s->nsc) {
    const long keep = s->o.screen_rows, most = keep + 1 + 2 * NX;
    const long cap = s->nsc * n * (ns < most ? ns : most);
    if (rows_reserve(&s->scr, cap, nut)) return -SQ_OUT_OF_MEMORY;
    const double t_rows = sq_now();
    const long got = lfm_screen(n, ns, s->nsc, s->screened, ro->G, ro->X, s->depends,
                                s->o.screen_margin, keep, s->scr.pos, cap);
    s->stats[ST_TIME_ROWS] += sq_now() - t_rows;
    if (got < 0) return -SQ_OUT_OF_MEMORY;
    s->scr.r = got;
  }
  for (long k = 0; k < n; ++k) /* the shared rows' values, ordered (step, constraint) */
    for (long l = 0; l < s->nL; ++l) {
      const double* g = ro->G + (s->shared[l] * n + k) * ns;
      s->gsh[k * s->nL + l] = np_max(g, ns);
    }
  const long size_mu = NGR * n * ns;
  for (int attempt = 0; attempt < 4; ++attempt) {
    if (attempt == 3) s->act.r = 0, s->n_act_shared = 0, s->n_bounds = 0;
    const double sigma = sq_convexify(s, ro);
    if (sigma < 0.0) return -SQ_NUMERICAL_ERROR;
    if (damping > 0.0)
      for (long i = 0; i < nut; ++i) s->Hq[i * (nut + 1)] += damping;
    const int got = sq_solve_qp(s, ro);
    memset(s->mu_next, 0, sizeof(double) * size_mu);
    if (got == SQ_OUT_OF_TIME) return SQ_OUT_OF_TIME;
    if (!got) return -SQ_QP_FAILED;
    const double* d = s->d;
    double curv = 0.0;
    for (long i = 0; i < nut; ++i) {
      double t = 0.0;
      for (long j = 0; j < nut; ++j) t += s->Hq[i * nut + j] * d[j];
      curv += d[i] * t;
    }
    s->curvature = curv;
    for (long e = 0; e < s->rows.r; ++e) {
      const long* p = s->rows.pos + 3 * e;
      s->mu_next[(p[0] * n + p[1]) * ns + p[2]] = s->lam_pos[e];
    }
    if (sigma == 0.0) return 1;
    const double tol = 1e-8;
    long keep_p = 0, keep_s = 0, keep_b = 0;
    int all = 1;
    for (long e = 0; e < s->act.r; ++e) { /* multipliers of the un-augmented QP */
      const long* p = s->act.pos + 3 * e;
      const double* a = s->act.a + e * nut;
      double lin_d = 0.0;
      for (long i = 0; i < nut; ++i) lin_d += a[i] * d[i];
      double* mu = s->mu_next + (p[0] * n + p[1]) * ns + p[2];
      const double lam = *mu + sigma * lin_d;
      const double g = ro->G[(p[0] * n + p[1]) * ns + p[2]];
      const int keep = lam >= -tol && g + lin_d - s->s_pos[p[0] * n + p[1]] >= -tol;
      *mu = fmax(lam, 0.0);
      if (keep) {
        memmove(s->act.pos + 3 * keep_p, p, sizeof(long) * 3);
        memmove(s->act.a + keep_p * nut, a, sizeof(double) * nut);
        s->act.g[keep_p] = s->act.g[e];
        ++keep_p;
      }
      all &= keep;
    }
    for (long e = 0; e < s->n_act_shared; ++e) {
      const long i = s->act_shared[e];
      const double* a = s->a_shared + i * nut;
      double sh_d = 0.0;
      for (long c = 0; c < nut; ++c) sh_d += a[c] * d[c];
      const int keep = s->lam_shared[i] + sigma * sh_d >= -tol
                       && s->gsh[i] + sh_d - s->s_shared[i] >= -tol;
      if (keep) s->act_shared[keep_s++] = i;
      all &= keep;
    }
    for (long e = 0; e < s->n_bounds; ++e) {
      const long i = s->bounds[e];
      const double un = u[i] + d[i];
      const int keep = un <= s->lower[i] + 1e-10 || un >= s->upper[i] - 1e-10;
      if (keep) s->bounds[keep_b++] = i;
      all &= keep;
    }
    if (all) return 1;
    s->act.r = keep_p, s->n_act_shared = keep_s, s->n_bounds = keep_b;
  }
  (void)nsh;
  return 1;
}

/* ------------------------------------------------------------------ where the time goes */

/* The parts above, each timed into its statistic (ST_TIME_*; sq_now costs ~25 ns). */
#define SQ_TIMED(stat, type, call)      \
  const double t_ = sq_now();           \
  type r_ = call;                       \
  s->stats[stat] += sq_now() - t_;      \
  return r_;

static ro_t* sq_evaluate(lfm_sqp* s, const double* u) {
  SQ_TIMED(ST_TIME_ROLLOUT, ro_t*, sq_evaluate_(s, u))
}
static int sq_linearise(lfm_sqp* s, const ro_t* ro) {
  SQ_TIMED(ST_TIME_LINEARISE, int, sq_linearise_(s, ro))
}
static void sq_hessian(lfm_sqp* s, const ro_t* ro) {
  const double t_ = sq_now();
  sq_hessian_(s, ro);
  s->stats[ST_TIME_HESSIAN] += sq_now() - t_;
}
static void sq_rows(lfm_sqp* s, const ro_t* ro, rows_t* r, long from) {
  const double t_ = sq_now();
  sq_rows_(s, ro, r, from);
  s->stats[ST_TIME_ROWS] += sq_now() - t_;
}
static double sq_convexify(lfm_sqp* s, const ro_t* ro) {
  SQ_TIMED(ST_TIME_CONVEXIFY, double, sq_convexify_(s, ro))
}
static int sq_solve_elastic(lfm_sqp* s) { SQ_TIMED(ST_TIME_QP, int, sq_solve_elastic_(s)) }
static int sq_solve_hard(lfm_sqp* s) { SQ_TIMED(ST_TIME_QP, int, sq_solve_hard_(s)) }
#undef SQ_TIMED

/* ------------------------------------------------------------------ one start */

typedef struct {
  ro_t* ro;         /* the current iterate */
  double prev_step; /* size of the last accepted full step (inf: none) */
  long acceptable;  /* accepted steps in a row with next to no decrease */
  double damping;   /* Levenberg-Marquardt term (trust_radius = 0) */
} start_t;

/* The linearisation, Hessian and QP step at the iterate (FastScenarioSolver._qp_step): 1, or
   a status ending the start (negated), or SQ_OUT_OF_TIME. The multipliers move to s->mu and
   the prediction of the next active set to s->act, s->act_shared. */
static int sq_qp_step(lfm_sqp* s, start_t* st) {
  const long nut = s->nut, n = s->n, ns = s->ns, nsh = s->nsh;
  sq_linearise(s, st->ro);
  sq_hessian(s, st->ro);
  int finite = 1;
  for (long e = 0; e < nut * nut && finite; ++e) finite = isfinite(s->H[e]);
  for (long i = 0; i < nut && finite; ++i) finite = isfinite(s->grad[i]);
  if (!finite) return -SQ_INVALID_DERIVATIVES;
  const int got = sq_newton_step(s, st->ro, st->damping);
  double* t = s->mu;
  s->mu = s->mu_next;
  s->mu_next = t;
  if (got != 1) return got;
  s->hard_first = s->o.elastic_on_demand && s->slack_sum <= s->o.add_tol;
  long kept = 0;
  if (rows_reserve(&s->act, s->rows.r, nut)) return -SQ_OUT_OF_MEMORY;
  for (long e = 0; e < s->rows.r; ++e) {
    const long* p = s->rows.pos + 3 * e;
    if (s->mu[(p[0] * n + p[1]) * ns + p[2]] > 1e-9 && s->s_pos[p[0] * n + p[1]] <= 1e-9) {
      memcpy(s->act.pos + 3 * kept, p, sizeof(long) * 3);
      ++kept;
    }
  }
  s->act.r = kept;
  s->n_act_shared = 0;
  for (long i = 0; i < nsh; ++i)
    if (s->lam_shared[i] > 1e-9 && s->s_shared[i] <= 1e-9) s->act_shared[s->n_act_shared++] = i;
  return 1;
}

typedef struct {
  double D, predicted;
  int cut;
} model_step_t;

static model_step_t sq_measure(lfm_sqp* s, const ro_t* ro) {
  model_step_t m;
  double gd = 0.0, dmax = 0.0;
  for (long i = 0; i < s->nut; ++i) {
    gd += s->grad[i] * s->d[i];
    dmax = fmax(dmax, fabs(s->d[i]) / s->range[i]);
  }
  m.D = gd + s->rho * (s->slack_sum - ro->slack);
  m.predicted = -(m.D + 0.5 * s->curvature);
  m.cut = s->o.trust_radius > 0.0 && dmax >= 0.99 * s->radius;
  return m;
}

static void sq_clip_step(const lfm_sqp* s, const double* u, const double* d, double t,
                         double* out) {
  for (long i = 0; i < s->nut; ++i) {
    const double v = u[i] + t * d[i];
    out[i] = v < s->lower[i] ? s->lower[i] : (v > s->upper[i] ? s->upper[i] : v);
  }
}

/* The second-order correction of the full step that gave trial
   (GlobalisationMixin._corrected): its rollout, or NULL. */
static ro_t* sq_corrected(lfm_sqp* s, const ro_t* ro, const ro_t* trial) {
  const long nut = s->nut, r = s->rows.r, n = s->n, ns = s->ns;
  double bpos[r + 1];
  for (long e = 0; e < r; ++e) {
    const long* p = s->rows.pos + 3 * e;
    const double* a = s->rows.a + e * nut;
    double ad = 0.0;
    for (long i = 0; i < nut; ++i) ad += a[i] * s->d[i];
    bpos[e] = -(trial->G[(p[0] * n + p[1]) * ns + p[2]] - ad);
  }
  sq_load(s, bpos);
  s->stats[ST_QP_SOLVES] += 1;
  int ok;
  if (s->q_hard) {
    s->stats[ST_QP_HARD] += 1;
    ok = sq_solve_hard(s);
  } else {
    ok = sq_solve_elastic(s);
  }
  if (!ok) return NULL;
  s->stats[ST_MERIT_EVALS] += 1;
  sq_clip_step(s, ro->u, s->qd, 1.0, s->u_try);
  return sq_evaluate(s, s->u_try);
}

/* The best of u + t d for t = 1, 2, 4, ... while the merit falls (GlobalisationMixin._expand);
   the accepted rollout in *acc, its step length returned (-1 when out of time). */
static double sq_expand(lfm_sqp* s, const ro_t* ro, ro_t** acc) {
  double t = 1.0;
  for (long e = 0; e < s->o.max_expand; ++e) {
    if (sq_now() >= s->deadline) return -1.0;
    sq_clip_step(s, ro->u, s->d, 2.0 * t, s->u_try);
    int same = 1; /* (np.array_equal) */
    for (long i = 0; i < s->nut && same; ++i) same = s->u_try[i] == (*acc)->u[i];
    if (same) break;
    ro_t* trial = sq_evaluate(s, s->u_try);
    s->stats[ST_MERIT_EVALS] += 1;
    if (!trial) return t;
    if (!(trial->merit < (*acc)->merit)) {
      ro_give(trial);
      break;
    }
    ro_give(*acc);
    *acc = trial;
    t *= 2.0;
  }
  return t;
}

/* The line search on the merit (GlobalisationMixin._line_search): the accepted rollout in
   *acc (NULL: none), its step length returned (-1 when out of time). */
static double sq_line_search(lfm_sqp* s, start_t* st, model_step_t m, ro_t** acc) {
  const lfm_sqp_options* o = &s->o;
  const ro_t* ro = st->ro;
  const int soc_ok = o->second_order_correction && s->rows.r > 0;
  double t = 1.0;
  *acc = NULL;
  while (t >= o->min_step) {
    if (sq_now() >= s->deadline) return -1.0;
    sq_clip_step(s, ro->u, s->d, t, s->u_try);
    ro_t* trial = sq_evaluate(s, s->u_try);
    s->stats[ST_MERIT_EVALS] += 1;
    if (!trial) return -2.0;
    if (trial->merit <= ro->merit + o->armijo * t * m.D) {
      *acc = trial;
      if (t == 1.0 && soc_ok && o->soc_below_ratio > 0.0 && trial->slack > ro->slack
          && ro->merit - trial->merit < o->soc_below_ratio * m.predicted) {
        ro_t* soc = sq_corrected(s, ro, trial);
        if (soc && soc->merit < trial->merit) {
          s->stats[ST_SOC_STEPS] += 1;
          ro_give(trial);
          *acc = soc;
        } else {
          ro_give(soc);
        }
      }
      break;
    }
    if (t == 1.0 && soc_ok && trial->slack > ro->slack) {
      ro_t* soc = sq_corrected(s, ro, trial);
      if (soc && soc->merit <= ro->merit + o->armijo * m.D) {
        s->stats[ST_SOC_STEPS] += 1;
        ro_give(trial);
        *acc = soc;
        break;
      }
      ro_give(soc);
    }
    ro_give(trial);
    t *= o->backtrack;
  }
  if (*acc && t == 1.0 && o->max_expand > 0 && ro->merit - (*acc)->merit >= -o->expand_ratio * m.D) {
    double dmax = 0.0;
    for (long i = 0; i < s->nut; ++i) dmax = fmax(dmax, fabs(s->d[i]));
    if (!isfinite(st->prev_step) || dmax > 0.5 * st->prev_step) t = sq_expand(s, ro, acc);
  }
  return t;
}

/* The trust region or damping after a step (GlobalisationMixin._adapt_region); returns
   whether the step reached the region. */
static int sq_adapt_region(lfm_sqp* s, start_t* st, model_step_t m, double t, double prev_merit,
                           double merit) {
  const lfm_sqp_options* o = &s->o;
  int at_radius = 0;
  if (o->trust_radius > 0.0) {
    double size = 0.0;
    for (long i = 0; i < s->nut; ++i) size = fmax(size, fabs(s->d[i]) / s->range[i]);
    at_radius = m.cut;
    const double ratio = m.predicted > 0.0 ? (prev_merit - merit) / m.predicted : 1.0;
    if (t < 1.0 || ratio < 0.25)
      s->radius = fmax(0.5 * t * size, o->min_trust_radius);
    else if (ratio > 0.25 && at_radius)
      s->radius = fmin(2.0 * s->radius, 1.0);
  } else if (t < o->damping_threshold) {
    st->damping = fmax(10.0 * st->damping, o->damping_init);
  } else if (t == 1.0) {
    st->damping = st->damping > 1e-3 * o->damping_init ? o->damping_decrease * st->damping : 0.0;
  }
  return at_radius;
}

/* Whether an extra start heads for the plan rival (RestartMixin._bound_for). */
static int sq_bound_for(const lfm_sqp* s, const double* rival, const double* u_prev,
                        const ro_t* ro, double bar) {
  double gap = 0.0, before = 0.0;
  for (long i = 0; i < s->nut; ++i) {
    gap = fmax(gap, fabs(ro->u[i] - rival[i]));
    before = fmax(before, fabs(u_prev[i] - rival[i]));
  }
  if (gap <= s->o.restart_same_tol) return 1;
  return gap <= s->o.restart_near_tol && gap < before && ro->merit > bar;
}

/* One SQP iteration (FastScenarioSolver._iteration and _accept): SQ_NONE to go on, else
   the status ending the start (SQ_OUT_OF_TIME inside it). */
static int sq_iteration(lfm_sqp* s, start_t* st, long iteration, double abandon_above,
                        const double* rival) {
  const lfm_sqp_options* o = &s->o;
  const int got = sq_qp_step(s, st);
  if (got == SQ_OUT_OF_TIME) return SQ_OUT_OF_TIME;
  if (got != 1) return -got;
  const model_step_t m = sq_measure(s, st->ro);
  ro_t* ro = st->ro;
  double dmax = 0.0;
  for (long i = 0; i < s->nut; ++i) dmax = fmax(dmax, fabs(s->d[i]));
  if (dmax <= o->step_tol) return SQ_SUCCEEDED;
  if (-m.D <= o->tol * (1.0 + fabs(ro->merit)) && !m.cut) return SQ_SUCCEEDED;
  if (iteration >= o->restart_probe && ro->merit + o->restart_optimism * m.D > abandon_above)
    return SQ_ABANDONED;
  ro_t* acc = NULL;
  const double t = sq_line_search(s, st, m, &acc);
  if (t == -1.0) {
    ro_give(acc);
    return SQ_OUT_OF_TIME;
  }
  if (t == -2.0) return SQ_OUT_OF_MEMORY;
  if (!acc) {
    if (-m.D <= 1e3 * o->tol * (1.0 + fabs(ro->merit))) return SQ_SUCCEEDED;
    return SQ_LINE_SEARCH_FAILED;
  }
  double size = 0.0;
  for (long i = 0; i < s->nut; ++i) size = fmax(size, fabs(acc->u[i] - ro->u[i]));
  const double slack_change = fabs(acc->slack - ro->slack);
  const double prev_merit = ro->merit;
  memcpy(s->u_prev, ro->u, sizeof(double) * s->nut); /* u before the step */
  ro_give(ro);
  st->ro = ro = acc;
  const int small = prev_merit - ro->merit <= o->acceptable_tol * (1.0 + fabs(ro->merit));
  st->acceptable = small ? st->acceptable + 1 : 0;
  if (st->acceptable >= o->acceptable_iter) return SQ_ACCEPTABLE;
  if (rival && sq_bound_for(s, rival, s->u_prev, ro, abandon_above)) return SQ_DUPLICATE;
  const int at_radius = sq_adapt_region(s, st, m, t, prev_merit, ro->merit);
  const double ratio = isfinite(st->prev_step) ? size / st->prev_step : 1.0;
  const double predicted_next = t == 1.0 && !at_radius ? size * fmin(ratio, 1.0) : INFINITY;
  st->prev_step = t == 1.0 ? size : INFINITY;
  if (predicted_next <= o->final_step_tol
      && (ro->slack <= o->add_tol || slack_change <= o->add_tol * (1.0 + ro->slack)))
    return SQ_SUCCEEDED;
  return SQ_NONE;
}

/* SQP iterations from u0 (FastScenarioSolver._sqp): the final rollout in *out, the status
   returned, the iterations in *iterations. */
static int sq_sqp(lfm_sqp* s, const double* u0, double abandon_above, const double* rival,
                  ro_t** out, long* iterations) {
  const lfm_sqp_options* o = &s->o;
  *iterations = 0;
  s->stats[ST_MERIT_EVALS] += 1;
  ro_t* ro = sq_evaluate(s, u0);
  *out = ro;
  if (!ro) return SQ_OUT_OF_MEMORY;
  /* the first start's is the warm start's merit (MPCSolution.usable; extra starts have a rival) */
  if (!rival) s->stats[ST_START_MERIT] = ro->merit, s->stats[ST_START_SLACK] = ro->slack;
  if (!isfinite(ro->merit)) return SQ_INVALID_START;
  memset(s->mu, 0, sizeof(double) * (NGR * s->n * s->ns + 1));
  s->act.r = 0, s->n_act_shared = 0;
  start_t st = {ro, INFINITY, 0, 0.0};
  int status = SQ_MAX_ITER;
  s->radius = o->trust_radius;
  if (o->elastic_on_demand != 2) /* (2, carried: as the last QP of the last solve left it) */
    s->hard_first = o->elastic_on_demand != 0;
  while (*iterations < o->max_iter) {
    if (sq_now() >= s->deadline) {
      status = SQ_WALL_TIME;
      break;
    }
    *iterations += 1;
    const int end = sq_iteration(s, &st, *iterations, abandon_above, rival);
    if (end == SQ_OUT_OF_TIME) {
      status = SQ_WALL_TIME;
      break;
    }
    if (end != SQ_NONE) {
      status = end;
      break;
    }
  }
  *out = st.ro;
  return status;
}

static int sq_success(int status) { return status == SQ_SUCCEEDED || status == SQ_ACCEPTABLE; }

/* Whether the plan drives a mirrored input beyond restart_threshold of its bound. */
static int sq_hard_mirror(const lfm_sqp* s, const double* u) {
  const double frac = s->o.restart_threshold - 1e-6;
  for (long k = 0; k < s->n; ++k)
    for (long a = 0; a < s->nmirror; ++a) {
      const long q = s->mirror[a];
      const double v = u[k * NU + q];
      if (v <= frac * s->lower[q] || v >= frac * s->upper[q]) return 1;
    }
  return 0;
}

/* The data of a solve into s: x0 (Ns, NX) as x0T (NX, Ns) and its averaged stage cost, W
   (Ns, N, NW) as (NW, N, Ns), backoff (N, NG) or NULL. */
static void sq_prepare(lfm_sqp* s, const double* x0, const double* W, const double* backoff) {
  const long n = s->n, ns = s->ns;
  double c0[ns + 1];
  for (long i = 0; i < ns; ++i) {
    const double* x = x0 + i * NX;
    double e[NX], c = 0.0;
    for (int m = 0; m < NX; ++m) {
      e[m] = x[m] - s->goal[m];
      s->x0T[m * ns + i] = x[m];
    }
    if (s->q_diagonal)
      for (int m = 0; m < NX; ++m) c += e[m] * s->Q0[m * (NX + 1)] * e[m];
    else
      for (int a = 0; a < NX; ++a)
        for (int b = 0; b < NX; ++b) c += e[a] * s->Q0[a * NX + b] * e[b];
    c0[i] = c;
  }
  s->cost0 = np_sum(c0, ns) / (double)ns;
  for (long i = 0; i < ns; ++i) /* the forces as (NW, N, Ns) */
    for (long k = 0; k < n; ++k)
      for (int a = 0; a < NW; ++a) s->W[(a * n + k) * ns + i] = W[(i * n + k) * NW + a];
  s->has_backoff = backoff != NULL;
  if (backoff)
    for (int j = 0; j < NG; ++j)
      for (long k = 0; k < n; ++k) s->backoff[j * n + k] = backoff[k * NG + j];
}

/* The SQP from u_start (clipped into s->lower, s->upper here) and its extra starts on the
   prepared data (FastScenarioSolver._run), within max_time of t_start: the best start's
   rollout in *out (NULL: out of memory), its status returned, the iterations of every start
   in *iterations. The statistics are reset first. */
static int sq_run(lfm_sqp* s, double t_start, double* u_start, ro_t** out, long* iterations) {
  const long n = s->n, nut = s->nut;
  s->deadline = isfinite(s->o.max_time) ? t_start + s->o.max_time : INFINITY;
  memset(s->stats, 0, sizeof(s->stats));
  s->stats[ST_START_MERIT] = s->stats[ST_START_SLACK] = INFINITY; /* (no start evaluated) */
  for (int i = 0; i < SQ_POOL; ++i) s->pool[i].used = 0;
  for (long i = 0; i < nut; ++i)
    u_start[i] = fmin(fmax(u_start[i], s->lower[i]), s->upper[i]);
  ro_t* ro = NULL;
  *iterations = 0;
  int status = sq_sqp(s, u_start, INFINITY, NULL, &ro, iterations);
  s->stats[ST_FIRST_STATUS] = status;
  s->stats[ST_FIRST_ITERATIONS] = (double)*iterations;
  s->stats[ST_RESTART_MIRROR] = s->stats[ST_RESTART_STRAIGHT] = -1.0; /* not tried */
  if (ro && status != SQ_OUT_OF_MEMORY) {
    /* the extra starts are chosen from the first plan (RestartMixin._restart_names) */
    const int hard = s->nmirror && sq_hard_mirror(s, ro->u);
    const int tried[2] = {hard && s->o.restart_mirror,
                          hard && s->o.restart_straight && ro->slack > s->o.add_tol};
    for (int which = 0; which < 2; ++which) {
      if (!tried[which]) continue;
      const int slot = which ? ST_RESTART_STRAIGHT : ST_RESTART_MIRROR;
      if (sq_now() >= s->deadline) {
        s->stats[slot] = 100.0; /* "no_time" */
        continue;
      }
      double guess[nut];
      memcpy(guess, ro->u, sizeof(double) * nut);
      for (long k = 0; k < n; ++k)
        for (long a = 0; a < s->nmirror; ++a) {
          double* v = guess + k * NU + s->mirror[a];
          *v = which ? 0.0 : -*v;
        }
      for (long i = 0; i < nut; ++i) guess[i] = fmin(fmax(guess[i], s->lower[i]), s->upper[i]);
      const double bar = ro->merit + s->o.restart_margin * fabs(ro->merit);
      double rival[nut];
      memcpy(rival, ro->u, sizeof(double) * nut);
      ro_t* ro2 = NULL;
      long it2 = 0;
      const int status2 = sq_sqp(s, guess, bar, rival, &ro2, &it2);
      *iterations += it2;
      const int better = ro2 && ro2->merit < ro->merit - 1e-12 * (1.0 + fabs(ro->merit));
      const int keep = better && (sq_success(status2) || !sq_success(status));
      s->stats[slot] = keep ? 99.0 : (double)status2; /* 99: "kept" */
      if (keep) {
        ro_give(ro);
        ro = ro2, status = status2;
      } else {
        ro_give(ro2);
      }
      if (status2 == SQ_OUT_OF_MEMORY) break;
    }
  }
  *out = ro;
  return ro ? status : SQ_OUT_OF_MEMORY;
}

/* The outputs of a solve that ended with the rollout ro (NULL: none) and status: the plan
   (also kept for the next warm start), the states, the statistics; returns the status. */
static int sq_finish(lfm_sqp* s, const ro_t* ro, int status, long iterations, double* u_out,
                     double* X_out, double* stats_out) {
  const long n = s->n, ns = s->ns, nut = s->nut;
  if (!ro) {
    for (long i = 0; i < nut; ++i) u_out[i] = NAN;
    s->stats[ST_MERIT] = INFINITY;
    memcpy(stats_out, s->stats, sizeof(s->stats));
    return status;
  }
  memcpy(u_out, ro->u, sizeof(double) * nut);
  memcpy(s->prev_u, ro->u, sizeof(double) * nut);
  s->has_prev = 1;
  if (X_out) memcpy(X_out, ro->X, sizeof(double) * (n + 1) * NX * ns);
  s->stats[ST_MERIT] = ro->merit;
  s->stats[ST_SLACK] = ro->slack;
  s->stats[ST_ITERATIONS] = (double)iterations;
  memcpy(stats_out, s->stats, sizeof(s->stats));
  return status;
}

#ifdef LFM_FEEDBACK
#include "feedback.c"
#endif

CASADI_SYMBOL_EXPORT int lfm_sqp_solve(lfm_sqp* s, const double* x0, const double* W,
    const double* u_guess, const double* backoff, double* u_out, double* X_out,
    double* stats_out) {
  /* x0 (Ns, NX), W (Ns, N, NW), u_guess (N NU) or NULL (the last plan shifted by one step,
     zeros at first), backoff (N, NG) or NULL; out: the plan u_out (N NU), the predicted states
     X_out (N + 1, NX, Ns) or NULL, stats_out (ST_COUNT). Returns the status. With a feedback
     prediction (feedback.c) u_guess is the reference plan and u_out the decision v. */
#ifdef LFM_FEEDBACK
  return fb_solve(s, x0, W, u_guess, backoff, u_out, X_out, stats_out);
#else
  const double t_start = sq_now();
  const long n = s->n, nut = s->nut;
  sq_prepare(s, x0, W, backoff);
  double u_start[nut];
  if (u_guess)
    memcpy(u_start, u_guess, sizeof(double) * nut);
  else if (s->has_prev)
    for (long k = 0; k < n; ++k)
      memcpy(u_start + k * NU, s->prev_u + (k + 1 < n ? k + 1 : n - 1) * NU, sizeof(double) * NU);
  else
    memset(u_start, 0, sizeof(double) * nut);
  ro_t* ro = NULL;
  long iterations = 0;
  const int status = sq_run(s, t_start, u_start, &ro, &iterations);
  return sq_finish(s, ro, status, iterations, u_out, X_out, stats_out);
#endif
}

/* Option name of the solver s to value from its next solve on (lfm_sqp_options_set, as
   acados' options_set): 0, or -1 for an unknown name. */
CASADI_SYMBOL_EXPORT int lfm_sqp_set_option(lfm_sqp* s, const char* name, double value) {
  return lfm_sqp_options_set(&s->o, name, value);
}

/* The Euler step x + dt f(x, u, w) of ns points under one input u (NU): states xT (NX, ns),
   forces W (NW, ns); X (2, NX, ns) gets the points, then their next states (a rollout of one
   step; with a feedback library, under the zero law). 0, or 1 if a generated function failed
   or out of memory. (The exported UKF's prediction.) */
CASADI_SYMBOL_EXPORT int lfm_step_points(long ns, const double* xT, const double* W,
                                         const double* u, double* X) {
  double row[ND], goal[NX], Wq[NX * NX], cost = 0.0;
  memset(row, 0, sizeof(row)); /* (feedback: K = 0, r = 0, R = 0, the rows inactive) */
  memcpy(row, u, sizeof(double) * NU);
  memset(goal, 0, sizeof(goal));
  memset(Wq, 0, sizeof(Wq));
  double* G = malloc(sizeof(double) * (NGR * ns + 1));
  if (!G) return 1;
  const int status = lfm_rollout(1, ns, xT, W, ns, ns, 1, row, goal, Wq, X, G, &cost, 1);
  free(G);
  return status != 0;
}

/* 1 if the library is that of a feedback prediction (lfm_sqp_set_law, lfm_sqp_law). */
CASADI_SYMBOL_EXPORT long lfm_sqp_feedback(void) {
#ifdef LFM_FEEDBACK
  return 1;
#else
  return 0;
#endif
}

CASADI_SYMBOL_EXPORT long lfm_sqp_stats_count(void) { return ST_COUNT; }

/* What the library was compiled with (the Python side checks its tables against these). */
CASADI_SYMBOL_EXPORT long lfm_sqp_status_count(void) { return SQ_COUNT; }
CASADI_SYMBOL_EXPORT long lfm_sqp_options_size(void) { return (long)sizeof(lfm_sqp_options); }

/* The constraints' Jacobian dg/dx at the state x into J (NG, NX) row-major (the exported
   controller's back-off); 0, or 1 if the generated function failed. */
CASADI_SYMBOL_EXPORT int lfm_constraint_jacobian(const double* x, double* J) {
#if NG > 0
  work_t wk;
  if (work_alloc(&wk)) return 1;
  const int status = CALL1(lfm_con_jac, x, J);
  work_free(&wk);
  return status;
#else
  (void)x;
  (void)J;
  return 0;
#endif
}
