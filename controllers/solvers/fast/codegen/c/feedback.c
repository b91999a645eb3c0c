/* The feedback prediction in the compiled SQP loop (included by sqp.c when the library is
   that of a feedback prediction, LFM_FEEDBACK): the C twin of the Python loop's
   controllers/solvers/fast/closed_loop.py and of controllers/feedback.py (feedback_law,
   nominal_inputs).

   A solve chooses its law as the Python loop does: the one given (lfm_sqp_set_law), else the
   finite-horizon TV-LQR of the cost's Q, R, Qf along the nominal rollout (mean initial state,
   mean force) of a reference plan: u_guess, else the nominal inputs of the last usable plan
   shifted by one step, else the plan of the same problem in open loop, solved first by the
   same loop with the zero law and every v_k bounded. Then the SQP on the decision v with the
   law (v_0 bounded; v_k free, or bounded with feedback_bounds = 1), and the nominal inputs
   of its plan (the next reference). */

/* Doubles of fb_work for a horizon n: the mean force (n, NW), the nominal states
   (n + 1, NX), the step Jacobians (n, NX, NX + NU). */
static long fb_work_size(long n) { return n * NW + (n + 1) * NX + n * NX * (NX + NU) + 1; }

/* The open-loop step F(x, u, w) (the closed-loop step's function with the zero law) into
   xn, or with jac its Jacobians [A, B] (NX, NX + NU) row-major into jac. 0, or 1 if the
   generated function failed. */
static int fb_open_step(work_t* wk, const double* x, const double* u, const double* w,
                        double* xn, double* jac) {
  double row[ND], p[(NP_STEP > NP_STEP_JAC ? NP_STEP : NP_STEP_JAC) + 1];
  double out[NX + NG + 1];
  memset(row, 0, sizeof(row));
  memcpy(row, u, sizeof(double) * NU);
  wk->arg[0] = row;
  wk->res[0] = p;
  if (jac) {
    if (lfm_step_jac_pre(wk->arg, wk->res, wk->iw, wk->w, 0)) return 1;
    wk->arg[0] = x, wk->arg[1] = row, wk->arg[2] = w, wk->arg[3] = p, wk->res[0] = jac;
    return lfm_step_jac(wk->arg, wk->res, wk->iw, wk->w, 0) != 0;
  }
  if (lfm_step_pre(wk->arg, wk->res, wk->iw, wk->w, 0)) return 1;
  wk->arg[0] = x, wk->arg[1] = row, wk->arg[2] = w, wk->arg[3] = p, wk->res[0] = out;
  if (lfm_step(wk->arg, wk->res, wk->iw, wk->w, 0)) return 1;
  memcpy(xn, out, sizeof(double) * NX);
  return 0;
}

/* The mean initial state (NX) and the mean force of every step (n, NW) of the solve's data
   (sq_prepare: x0T, W), each a sum in scenario order over Ns (as NumPy's mean(axis=0)). */
static void fb_means(const lfm_sqp* s, double* xbar, double* wbar) {
  const long n = s->n, ns = s->ns;
  for (int m = 0; m < NX; ++m) {
    double t = 0.0;
    for (long i = 0; i < ns; ++i) t += s->x0T[m * ns + i];
    xbar[m] = t / (double)ns;
  }
  for (long k = 0; k < n; ++k)
    for (int a = 0; a < NW; ++a) {
      double t = 0.0;
      for (long i = 0; i < ns; ++i) t += s->W[(a * n + k) * ns + i];
      wbar[k * NW + a] = t / (double)ns;
    }
}

/* M^+ b for the symmetric M (NU, NU) and the columns of b (NU, NX): the least-squares
   solution of least norm (NumPy's lstsq, its cutoff: eigenvalues within NU eps of the
   largest count as zero) into out. 0, or 1 if the eigen-decomposition failed. */
static int fb_pinv_solve(const double* M, const double* b, double* out) {
  double w[NU], V[NU * NU], work[NU * NU + 3 * NU];
  if (dq_eigh(NU, M, w, V, work)) return 1;
  double top = 0.0;
  for (int i = 0; i < NU; ++i) top = fmax(top, fabs(w[i]));
  const double cut = DBL_EPSILON * NU * top;
  memset(out, 0, sizeof(double) * NU * NX);
  for (int e = 0; e < NU; ++e) {
    if (!(fabs(w[e]) > cut)) continue;
    for (int c = 0; c < NX; ++c) {
      double t = 0.0; /* v_e' b[:, c] / w_e */
      for (int q = 0; q < NU; ++q) t += V[q * NU + e] * b[q * NX + c];
      t /= w[e];
      for (int q = 0; q < NU; ++q) out[q * NX + c] += V[q * NU + e] * t;
    }
  }
  return 0;
}

/* One step of the Riccati recursion back from P (NX, NX): the gain K (NU, NX) of step k with
   the Jacobians A (NX, NX), B (NX, NU), and P replaced by Q + K' R K + (A + B K)' P (A + B K),
   symmetrised (tvlqr_gains). 0, or 1. */
static int fb_riccati_step(const lfm_sqp* s, const double* A, const double* B, double* P,
                           double* K) {
  double PB[NX * NU], PA[NX * NX], M[NU * NU], rhs[NU * NX], Acl[NX * NX], T[NX * NX];
  for (int a = 0; a < NX; ++a) {
    for (int q = 0; q < NU; ++q) {
      double t = 0.0;
      for (int m = 0; m < NX; ++m) t += P[a * NX + m] * B[m * NU + q];
      PB[a * NU + q] = t;
    }
    for (int c = 0; c < NX; ++c) {
      double t = 0.0;
      for (int m = 0; m < NX; ++m) t += P[a * NX + m] * A[m * NX + c];
      PA[a * NX + c] = t;
    }
  }
  for (int p = 0; p < NU; ++p) {
    for (int q = 0; q < NU; ++q) {
      double t = s->R[p * NU + q];
      for (int m = 0; m < NX; ++m) t += B[m * NU + p] * PB[m * NU + q];
      M[p * NU + q] = t;
    }
    for (int c = 0; c < NX; ++c) {
      double t = 0.0;
      for (int m = 0; m < NX; ++m) t += B[m * NU + p] * PA[m * NX + c];
      rhs[p * NX + c] = t;
    }
  }
  if (fb_pinv_solve(M, rhs, K)) return 1;
  for (int e = 0; e < NU * NX; ++e) K[e] = -K[e];
  for (int a = 0; a < NX; ++a)
    for (int c = 0; c < NX; ++c) {
      double t = A[a * NX + c];
      for (int q = 0; q < NU; ++q) t += B[a * NU + q] * K[q * NX + c];
      Acl[a * NX + c] = t;
    }
  for (int a = 0; a < NX; ++a) /* T = P Acl */
    for (int c = 0; c < NX; ++c) {
      double t = 0.0;
      for (int m = 0; m < NX; ++m) t += P[a * NX + m] * Acl[m * NX + c];
      T[a * NX + c] = t;
    }
  double Pn[NX * NX];
  for (int a = 0; a < NX; ++a)
    for (int c = 0; c < NX; ++c) {
      double t = s->Q0[a * NX + c];
      for (int p = 0; p < NU; ++p)
        for (int q = 0; q < NU; ++q) t += K[p * NX + a] * s->R[p * NU + q] * K[q * NX + c];
      for (int m = 0; m < NX; ++m) t += Acl[m * NX + a] * T[m * NX + c];
      Pn[a * NX + c] = t;
    }
  for (int a = 0; a < NX; ++a)
    for (int c = 0; c < NX; ++c) P[a * NX + c] = 0.5 * (Pn[a * NX + c] + Pn[c * NX + a]);
  return 0;
}

/* The law of a reference plan ref (N NU; feedback_law): clipped into the input bounds, its
   nominal rollout r from the mean initial state under the mean forces, and the TV-LQR gains
   along it (K_0 = 0), into s->law_K, s->law_r. 0, or 1 if a generated function or an
   eigen-decomposition failed. */
static int fb_law(lfm_sqp* s, const double* ref, const double* xbar, const double* wbar) {
  const long n = s->n;
  double* X = s->fb_work + n * NW;          /* (n + 1, NX) */
  double* J = X + (n + 1) * NX;             /* (n, NX, NX + NU) */
  work_t wk;
  if (work_alloc(&wk)) return 1;
  int fail = 0;
  double u[NU];
  memcpy(X, xbar, sizeof(double) * NX);
  for (long k = 0; k < n && !fail; ++k) {
    for (int q = 0; q < NU; ++q)
      u[q] = fmin(fmax(ref[k * NU + q], s->lower_all[k * NU + q]), s->upper_all[k * NU + q]);
    fail = fb_open_step(&wk, X + k * NX, u, wbar + k * NW, X + (k + 1) * NX, NULL)
           || fb_open_step(&wk, X + k * NX, u, wbar + k * NW, NULL, J + k * NX * (NX + NU));
  }
  work_free(&wk);
  if (fail) return 1;
  double P[NX * NX], A[NX * NX], B[NX * NU];
  memcpy(P, s->Wq + (n - 1) * NX * NX, sizeof(P)); /* Qf */
  memset(s->law_K, 0, sizeof(double) * n * NU * NX);
  for (long k = n - 1; k >= 1; --k) {
    const double* Jk = J + k * NX * (NX + NU); /* A (NX, NX) then B (NX, NU), row-major */
    memcpy(A, Jk, sizeof(A));
    memcpy(B, Jk + NX * NX, sizeof(B));
    if (fb_riccati_step(s, A, B, P, s->law_K + k * NU * NX)) return 1;
  }
  memcpy(s->law_r, X, sizeof(double) * n * NX);
  return 0;
}

/* The law s->law_K, s->law_r into the data rows, and the bounds of v: every v_k (all), or
   v_0 only. A step's input rows count unless they repeat the hard bounds (K_k = 0 on a
   bounded v_k). */
static void fb_use_law(lfm_sqp* s, int all) {
  s->lower = all ? s->lower_all : s->lower_first;
  s->upper = all ? s->upper_all : s->upper_first;
  for (long k = 0; k < s->n; ++k) {
    double* row = s->D + k * ND;
    const double* K = s->law_K + k * NU * NX;
    int zero = 1;
    for (int e = 0; e < NU * NX; ++e) zero &= K[e] == 0.0;
    memcpy(row + NU, K, sizeof(double) * NU * NX);
    memcpy(row + NU + NU * NX, s->law_r + k * NX, sizeof(double) * NX);
    row[NDF + NU * NU] = (k == 0 || all) && zero ? 0.0 : 1.0;
  }
}

/* The inputs the plan v applies along its nominal rollout (mean initial state, mean force)
   into out (N NU): v_0, then v_k + K_k (x_k - r_k) (nominal_inputs). 0, or 1. */
static int fb_nominal(lfm_sqp* s, const double* v, const double* xbar, const double* wbar,
                      double* out) {
  work_t wk;
  if (work_alloc(&wk)) return 1;
  double x[NX], xn[NX];
  int fail = 0;
  memcpy(x, xbar, sizeof(x));
  for (long k = 0; k < s->n && !fail; ++k) {
    double* u = out + k * NU;
    for (int q = 0; q < NU; ++q) {
      double t = v[k * NU + q];
      if (k)
        for (int m = 0; m < NX; ++m)
          t += s->law_K[(k * NU + q) * NX + m] * (x[m] - s->law_r[k * NX + m]);
      u[q] = t;
    }
    fail = fb_open_step(&wk, x, u, wbar + k * NW, xn, NULL);
    memcpy(x, xn, sizeof(x));
  }
  work_free(&wk);
  return fail;
}

/* The plan p (N NU) one step on, into out. */
static void fb_shifted(const lfm_sqp* s, const double* p, double* out) {
  for (long k = 0; k < s->n; ++k)
    memcpy(out + k * NU, p + (k + 1 < s->n ? k + 1 : s->n - 1) * NU, sizeof(double) * NU);
}

/* The input rows' slack of the rollout ro (NumPy's sum of the rows' largest values, >= 0). */
static double fb_input_slack(const lfm_sqp* s, const ro_t* ro) {
  const long n = s->n, rows = (NGR - NG) * n;
  double mx[rows + 1];
  for (long jk = 0; jk < rows; ++jk) {
    const double m = np_max(ro->G + (NG * n + jk) * s->ns, s->ns);
    mx[jk] = m != m ? NAN : (m > 0.0 ? m : 0.0);
  }
  return np_sum(mx, rows);
}

/* lfm_sqp_solve of a feedback library (the module comment). */
static int fb_solve(lfm_sqp* s, const double* x0, const double* W, const double* u_guess,
                    const double* backoff, double* u_out, double* X_out, double* stats_out) {
  const long n = s->n, nut = s->nut;
  const double t0 = sq_now(); /* (one time limit for the whole solve, the reference's included) */
  sq_prepare(s, x0, W, backoff);
  double xbar[NX], *wbar = s->fb_work, ref[nut], u_start[nut];
  fb_means(s, xbar, wbar);
  int has_ref = 0;
  double source = 0.0, ref_status = -1.0, ref_iterations = 0.0, ref_time = 0.0, gain = 0.0;
  if (u_guess) {
    memcpy(ref, u_guess, sizeof(ref));
    has_ref = 1, source = 1.0;
  } else if (s->has_ref) {
    fb_shifted(s, s->ref_plan, ref);
    has_ref = 1, source = 2.0;
  }
  if (!s->law_given) {
    if (!has_ref) { /* the open-loop plan of the problem */
      const double t1 = sq_now();
      memset(s->law_K, 0, sizeof(double) * n * NU * NX);
      memset(s->law_r, 0, sizeof(double) * n * NX);
      fb_use_law(s, 1);
      if (s->has_last_open)
        fb_shifted(s, s->last_open, u_start);
      else
        memset(u_start, 0, sizeof(u_start));
      ro_t* ro = NULL;
      long it = 0;
      const int st = sq_run(s, t0, u_start, &ro, &it);
      if (!ro) return sq_finish(s, NULL, SQ_OUT_OF_MEMORY, 0, u_out, X_out, stats_out);
      memcpy(ref, ro->u, sizeof(ref));
      memcpy(s->last_open, ro->u, sizeof(ref));
      s->has_last_open = 1, has_ref = 1, source = 3.0;
      ref_status = st, ref_iterations = (double)it, ref_time = sq_now() - t1;
    }
    const double t2 = sq_now();
    if (fb_law(s, ref, xbar, wbar)) {
      memset(s->stats, 0, sizeof(s->stats));
      s->stats[ST_START_MERIT] = INFINITY;
      return sq_finish(s, NULL, SQ_NUMERICAL_ERROR, 0, u_out, X_out, stats_out);
    }
    gain = sq_now() - t2;
  }
  s->law_given = 0;
  fb_use_law(s, s->o.feedback_bounds == 1);
  if (has_ref) /* (the reference inside the input bounds; sq_run clips into v's) */
    for (long i = 0; i < nut; ++i)
      u_start[i] = fmin(fmax(ref[i], s->lower_all[i]), s->upper_all[i]);
  else if (s->has_last_v)
    fb_shifted(s, s->last_v, u_start);
  else
    memset(u_start, 0, sizeof(u_start));
  ro_t* ro = NULL;
  long iterations = 0;
  const int status = sq_run(s, t0, u_start, &ro, &iterations);
  s->stats[ST_LAW_SOURCE] = source;
  s->stats[ST_REFERENCE_STATUS] = ref_status;
  s->stats[ST_REFERENCE_ITERATIONS] = ref_iterations;
  s->stats[ST_REFERENCE_TIME] = ref_time;
  s->stats[ST_GAIN_TIME] = gain;
  if (ro) {
    s->stats[ST_INPUT_SLACK] = fb_input_slack(s, ro);
    const int usable = sq_success(status) || (isfinite(ro->merit)
                                              && ro->merit < s->stats[ST_START_MERIT]);
    const int nominal = !fb_nominal(s, ro->u, xbar, wbar, s->nominal);
    memcpy(s->last_v, ro->u, sizeof(ref));
    s->has_last_v = 1;
    s->has_ref = usable && nominal;
    if (s->has_ref) memcpy(s->ref_plan, s->nominal, sizeof(ref));
  }
  return sq_finish(s, ro, status, iterations, u_out, X_out, stats_out);
}

CASADI_SYMBOL_EXPORT int lfm_sqp_set_law(lfm_sqp* s, const double* K, const double* r) {
  /* The law of the next solve: K (N, NU, NX) with K_0 = 0, r (N, NX). */
  memcpy(s->law_K, K, sizeof(double) * s->n * NU * NX);
  memcpy(s->law_r, r, sizeof(double) * s->n * NX);
  s->law_given = 1;
  return 0;
}

CASADI_SYMBOL_EXPORT int lfm_sqp_law(const lfm_sqp* s, double* K, double* r, double* nominal) {
  /* The last solve's law K (N, NU, NX), r (N, NX) and its plan's nominal inputs (N NU); any
     may be NULL. */
  if (K) memcpy(K, s->law_K, sizeof(double) * s->n * NU * NX);
  if (r) memcpy(r, s->law_r, sizeof(double) * s->n * NX);
  if (nominal) memcpy(nominal, s->nominal, sizeof(double) * s->nut);
  return 0;
}
