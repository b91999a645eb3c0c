/* The adjoint lambda_k = dl/dx_{k+1} + Jg_k' mu + A_{k+1}' lambda_{k+1} of step k of scenario
   i (the last term ATl_next, from step k + 1's lfm_step_curv; none at the last step) into
   lam. */
static inline void step_adjoint(long n, long ns, long k, long i, const double* X,
    const double* Jg, const double* mu, const double* goal, const double* Wq, int diag,
    double scale, const double* ATl_next, double* lam) {
  double x[NX];
  load_state(X, k + 1, ns, i, x);
  weighted(x, goal, Wq + k * NX * NX, diag, scale, lam);
#if NG > 0
  if (mu) {
    const double* Jk = Jg + (k * ns + i) * GR_NNZ;
    for (int j = 0; j < NG; ++j) {
      const double mj = mu[(j * n + k) * ns + i];
      if (mj != 0.0)
        for (int e = G_PTR[j]; e < G_PTR[j + 1]; ++e) lam[G_COL[e]] += mj * Jk[e];
    }
  }
#else
  (void)Jg; (void)mu; (void)n;
#endif
  if (ATl_next)
    for (int m = 0; m < NX; ++m) lam[m] += ATl_next[m];
}

/* The curvature V_j of everything from state x_j (j = 1..N) on, of scenario i, into V:
   scale Wq_j + the Hessian of mu' g at x_j + Pj = A_j' V_{j+1} A_j + M_j[x, x] (step j's
   lfm_step_curv, row-major (NX, NX); NULL at j = N); entry a at Mxx[a ms]. */
static inline int state_curvature(work_t* wkp, long n, long ns, long j, long i, const double* X,
    const double* Pj, const double* mu, const double* Wq, double scale, double* Mxx, long ms) {
  work_t wk = *wkp;
  const double* Wk = Wq + (j - 1) * NX * NX;
  for (int a = 0; a < NX * NX; ++a) Mxx[a * ms] = scale * Wk[a];
  if (Pj)
    for (int a = 0; a < NX * NX; ++a) Mxx[a * ms] += Pj[a];
#if NG > 0
  if (mu) {
    double mk[NG], hg[NX * NX], x[NX];
    int any = 0;
    for (int q = 0; q < NG; ++q) any |= (mk[q] = mu[(q * n + j - 1) * ns + i]) != 0.0;
    if (any) {
      load_state(X, j, ns, i, x);
      if (CALL2(lfm_con_hess, x, mk, hg)) return 1;
      for (int r = 0; r < NX; ++r)
        for (int c = 0; c < NX; ++c) Mxx[(r * NX + c) * ms] += hg[r + c * NX];
    }
  }
#else
  (void)X; (void)mu; (void)wk; (void)n; (void)ns; (void)i;
#endif
  return 0;
}

/* Rows c < cols of column block k of H (its entries H[c, k NU + q]) += Sk' Y: Sk (NX, cols)
   row-major with row stride bs, Y (NX, NU). */
static inline void add_columns(double* H, long nut, long k, long cols, const double* Sk,
                               long bs, const double* Y) {
  for (long c = 0; c < cols; ++c) {
    double s[NU] = {0.0};
    for (int r = 0; r < NX; ++r) {
      const double v = Sk[r * bs + c];
      for (int q = 0; q < NU; ++q) s[q] += v * Y[r * NU + q];
    }
    for (int q = 0; q < NU; ++q) H[c * nut + k * NU + q] += s[q];
  }
}

/* Scenarios i0 <= i < i1 of lfm_hessian (see there); their terms added into H (upper
   triangle of blocks; the diagonal blocks whole). One backward sweep over the steps, all
   scenarios (of the chunk) at each, so the arrays are read in their (step, scenario) order;
   what a scenario carries from step k + 1 to step k (A_{k+1}' lambda_{k+1} and
   P_{k+1} = A_{k+1}' V_{k+2} A_{k+1} + M_{k+1}[x, x]) is kept in carry (whole arrays,
   (Ns, CARRY) twice: a chunk uses its own scenarios' rows). */
#define CARRY (NX + NX * NX)
#define CURV_XU (NX * NX)                /* lfm_step_curv: offset of A' V B + M[x, u] */
#define CURV_UU (CURV_XU + NX * NU)      /* of B' V B + M[u, u] */
#define CURV_ATL (CURV_UU + NU * NU)     /* of A' lambda */
#define CURV_OUT (CURV_ATL + NX)         /* lfm_step_curv's values */

/* Scenario i at step k: its adjoint lambda_k and the curvature V_{k+1} (entry a at V[a vs];
   from what it carried from step k + 1, in next). */
static inline int hessian_point_in(work_t* wkp, long n, long ns, long k, long i,
    const double* X, const double* Jg, const double* mu, const double* goal, const double* Wq,
    int diag, double scale, const double* next, double* lam, double* V, long vs) {
  const double* carried = k + 1 < n ? next + i * CARRY : NULL; /* none at the last step */
  const double* ATl_next = carried;                     /* A_{k+1}' lambda_{k+1} */
  const double* P_next = carried ? carried + NX : NULL; /* P_{k+1} */
  step_adjoint(n, ns, k, i, X, Jg, mu, goal, Wq, diag, scale, ATl_next, lam);
  /* V_{k+1} = scale Wq + Hessian of mu' g at x_{k+1} + P_{k+1}: the curvature of
     everything after x_{k+1} as a function of x_{k+1} */
  return state_curvature(wkp, n, ns, k + 1, i, X, P_next, mu, Wq, scale, V, vs);
}

#ifdef LFM_FEEDBACK
/* The input's terms at step k (the data row d; its cost (1/Ns) u' R u with scale = 2/Ns and
   its rows' multipliers mu) that the closed-loop step's function leaves out: u = v + K (x - r)
   is linear in (x, v), so they add scale K' R K to the curvature carried to x_k (mine + NX),
   scale K' R to the cross terms (xu) and K' (scale R u + mu_upper - mu_lower) to the
   adjoint carried (mine); the input block's scale R is added once per block by the caller of
   lfm_hessian (as the open-loop input cost's 2 R). */
static inline void fb_point_terms(long n, long ns, long k, long i, const double* X,
    const double* d, const double* mu, double scale, double* mine, double* xu) {
  double x[NX], u[NU], g[NU], KR[NX * NU];
  load_state(X, k, ns, i, x);
  fb_applied(x, 1, d, u);
  for (int q = 0; q < NU; ++q) {
    double t = 0.0;
    for (int p = 0; p < NU; ++p) t += d[D_RW + q * NU + p] * u[p];
    g[q] = scale * t;
    if (mu && d[D_ACTIVE] != 0.0)
      g[q] += mu[((NG + q) * n + k) * ns + i] - mu[((NG + NU + q) * n + k) * ns + i];
  }
  for (int m = 0; m < NX; ++m) {
    double t = 0.0;
    for (int q = 0; q < NU; ++q) t += d[D_K + q * NX + m] * g[q];
    mine[m] += t;
    for (int q = 0; q < NU; ++q) {
      double c = 0.0; /* (K' R)[m, q] */
      for (int p = 0; p < NU; ++p) c += d[D_K + p * NX + m] * d[D_RW + p * NU + q];
      KR[m * NU + q] = scale * c;
      xu[m * NU + q] += KR[m * NU + q];
    }
  }
  for (int a = 0; a < NX; ++a)
    for (int b = 0; b < NX; ++b) {
      double c = 0.0;
      for (int q = 0; q < NU; ++q) c += KR[a * NU + q] * d[D_K + q * NX + b];
      mine[NX + a * NX + b] += c;
    }
}
#endif

/* Scenario i at step k, given lfm_step_curv's values (entry e at o[e os]): what it carries
   to step k - 1 (into now) and its terms of H. With feedback, also the input's terms
   (fb_point_terms: X, the data row d, the multipliers mu and scale). */
static inline void hessian_point_out(long n, long ns, long k, long i, const double* S,
    const double* o, long os, double* now, double* H, const double* X, const double* d,
    const double* mu, double scale) {
  const long nut = n * NU;
  double* mine = now + i * CARRY;
  double xu[NX * NU];
  for (int e = 0; e < NX; ++e) mine[e] = o[(CURV_ATL + e) * os];
  for (int e = 0; e < NX * NX; ++e) mine[NX + e] = o[e * os];
  for (int e = 0; e < NX * NU; ++e) xu[e] = o[(CURV_XU + e) * os];
#ifdef LFM_FEEDBACK
  fb_point_terms(n, ns, k, i, X, d, mu, scale, mine, xu);
#else
  (void)X, (void)d, (void)mu, (void)scale;
#endif
  /* diagonal block: B_k' V_{k+1} B_k + M_k[u, u] */
  for (int p = 0; p < NU; ++p)
    for (int q = 0; q < NU; ++q)
      H[(k * NU + p) * nut + k * NU + q] += o[(CURV_UU + p * NU + q) * os];
  /* blocks (a, k), a < k: S_k' (A_k' V_{k+1} B_k + M_k[x, u]), S_k = dx_k/du_0..k-1
     (column block a: A_{k-1} ... A_{a+1} B_a) */
  if (k > 0)
    add_columns(H, nut, k, k * NU, S + S_OFF(k - 1, ns) + i * NXS * k * NU, k * NU, xu);
}

#ifdef LFM_STEP_CURV_INLINE
#define CURV_BLOCK 32 /* scenarios whose lfm_step_curv is evaluated together */
/* lfm_step_curv of nb (<= CURV_BLOCK) scenarios of one step in one vectorisable loop: their
   states x (stride ns), forces w (scenario stride si, component stride sa), adjoints and
   curvatures from Lb and Vb and the values into Ob (entry e of scenario b at e CURV_BLOCK +
   b). On its own, so that only this loop has the x86-64-v3 version (LFM_CLONES). */
LFM_CLONES static void curv_block(long nb, const double* x, long ns, const double* u,
    const double* w, long sa, long si, const double* p, const double* Lb, const double* Vb,
    double* Ob) {
#pragma omp simd
  for (long b = 0; b < nb; ++b)
    lfm_step_curv_inline(x + b, ns, u, w + b * si, sa, p, Lb + b, Vb + b, CURV_BLOCK, Ob + b);
}

static int hessian_chunk(work_t* wkp, long n, long ns, long i0, long i1, const double* X,
    const double* W, long sa, long sk, long si, const double* u, const double* P,
    const double* S, const double* Jg, const double* mu, const double* goal, const double* Wq,
    int diag, double scale, double* carry, double* H) {
  double lam[NX];
  double Lb[NX * CURV_BLOCK], Vb[NX * NX * CURV_BLOCK], Ob[CURV_OUT * CURV_BLOCK];
  double* now = carry;               /* step k: A_k' lambda_k, P_k */
  double* next = carry + ns * CARRY; /* step k + 1 */
  int status = 0;
  for (long k = n - 1; k >= 0 && !status; --k) {
    for (long b0 = i0; b0 < i1 && !status; b0 += CURV_BLOCK) {
      const long nb = b0 + CURV_BLOCK < i1 ? CURV_BLOCK : i1 - b0;
      for (long b = 0; b < nb && !status; ++b) {
        status = hessian_point_in(wkp, n, ns, k, b0 + b, X, Jg, mu, goal, Wq, diag, scale,
                                  next, lam, Vb + b, CURV_BLOCK);
        for (int e = 0; e < NX; ++e) Lb[e * CURV_BLOCK + b] = lam[e];
      }
      if (status) break;
      curv_block(nb, X + k * NX * ns + b0, ns, u + k * ND, W + k * sk + b0 * si, sa, si,
                 P + k * NP_STEP_CURV, Lb, Vb, Ob);
      for (long b = 0; b < nb; ++b)
        hessian_point_out(n, ns, k, b0 + b, S, Ob + b, CURV_BLOCK, now, H, X, u + k * ND, mu,
                          scale);
    }
    double* t = now; now = next; next = t;
  }
  return status;
}
#else
static int hessian_chunk(work_t* wkp, long n, long ns, long i0, long i1, const double* X,
    const double* W, long sa, long sk, long si, const double* u, const double* P,
    const double* S, const double* Jg, const double* mu, const double* goal, const double* Wq,
    int diag, double scale, double* carry, double* H) {
  work_t wk = *wkp;
  double lam[NX], V[NX * NX], out[CURV_OUT], x[NX], wv[NW + 1];
  double* now = carry;               /* step k: A_k' lambda_k, P_k */
  double* next = carry + ns * CARRY; /* step k + 1 */
  int status = 0;
  for (long k = n - 1; k >= 0 && !status; --k) {
    for (long i = i0; i < i1 && !status; ++i) {
      status = hessian_point_in(wkp, n, ns, k, i, X, Jg, mu, goal, Wq, diag, scale, next, lam,
                                V, 1);
      if (status) break;
      load_state(X, k, ns, i, x);
      gather(W, sa, sk, si, k, i, wv);
      status = CALL6(lfm_step_curv, x, u + k * ND, wv, P + k * NP_STEP_CURV, lam, V, out);
      if (status) break;
      hessian_point_out(n, ns, k, i, S, out, 1, now, H, X, u + k * ND, mu, scale);
    }
    double* t = now; now = next; next = t;
  }
  return status;
}
#endif

/* The scratch lfm_hessian needs for Ns scenarios, in doubles. */
CASADI_SYMBOL_EXPORT long lfm_hessian_scratch(long ns) { return 2 * ns * CARRY + 1; }

CASADI_SYMBOL_EXPORT int lfm_hessian(long n, long ns, const double* X, const double* W,
    long sa, long sk, long si, const double* u, const double* S,
    const double* Jg, const double* mu, const double* goal, const double* Wq, double scale,
    double* H, double* carry, long nthreads) {
  /* sum over scenarios of the Hessian of (cost + mu' G) w.r.t. u, without the input cost.
     Per scenario a backward recursion (condensing, O(N^2) in the horizon where the sum
     sum_j S_j' Mxx_j S_j is O(N^3)): with V_{k+1} the curvature of everything after x_{k+1}
     w.r.t. x_{k+1} (V_N = Mxx_N, V_j = Mxx_j + A_j' V_{j+1} A_j), block (k, k) is
     B_k' V_{k+1} B_k + M_k[u, u] and the blocks (a, k), a < k, are
     S_k' (A_k' V_{k+1} B_k + M_k[x, u]) with the sensitivities S_k of x_k (column block a:
     A_{k-1} ... A_{a+1} B_a). Mxx_j = scale Wq_j + M_j[x, x] + the Hessian of mu' g at x_j,
     M_k the Hessian of lambda_k' F at (x_k, u_k) with the adjoints lambda_k. The products
     with A_k and B_k and M_k come from one generated function per point, lfm_step_curv
     (the Jacobians' structural zeros skipped, their subexpressions shared). Upper
     triangle, then mirrored. Each entry sums its terms over the scenarios in ascending
     order (with T chunks: per chunk, then the chunks' sums in order). carry: the caller's
     scratch of lfm_hessian_scratch(ns) doubles (kept by the caller: a fresh 1.6 MB block
     per call at Ns = 5000 cost ~80 page faults). */
  work_t wk;
  if (work_alloc(&wk)) return 1;
  const long nut = n * NU, T = chunks(nthreads, ns);
  const int diag = diagonal(Wq, n);
  double* P = parametric(&wk, lfm_step_curv_pre, NP_STEP_CURV, n, u);
  double* part = T > 1 ? calloc((T - 1) * nut * nut + 1, sizeof(double)) : NULL;
  int* st = malloc(T * sizeof(int));
  if (!P || !st || (T > 1 && !part)) {
    free(P); free(part); free(st); work_free(&wk);
    return 1;
  }
  int status = 0;
  memset(H, 0, nut * nut * sizeof(double));
  if (T == 1) {
    status = hessian_chunk(&wk, n, ns, 0, ns, X, W, sa, sk, si, u, P, S, Jg, mu, goal, Wq,
                           diag, scale, carry, H);
  } else {
#pragma omp parallel for num_threads(T) schedule(static, 1)
    for (long t = 0; t < T; ++t) {
      work_t mine;
      st[t] = work_alloc(&mine) ? 1
          : hessian_chunk(&mine, n, ns, CHUNK(ns, t, T), CHUNK(ns, t + 1, T), X, W, sa, sk, si,
                          u, P, S, Jg, mu, goal, Wq, diag, scale, carry,
                          t ? part + (t - 1) * nut * nut : H);
      work_free(&mine);
    }
    for (long t = 0; t < T; ++t) status |= st[t];
    for (long t = 1; t < T; ++t)
      for (long e = 0; e < nut * nut; ++e) H[e] += part[(t - 1) * nut * nut + e];
  }
  for (long a = 0; a < nut; ++a)
    for (long b = 0; b < a; ++b) H[a * nut + b] = H[b * nut + a];
  free(P);
  free(part);
  free(st);
  work_free(&wk);
  return status;
}
