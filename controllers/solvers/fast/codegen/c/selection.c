/* The row selection (the NumPy reference is controllers/solvers/fast/screening.py): the keep
   best values of a group, best first, ranked by larger value, then lower scenario index.
   The scenarios come in ascending order, so a new value ranks after an equal one. */
static void top_insert(double* tv, long* ti, long* cnt, long keep, double v, long i) {
  long c = *cnt;
  if (c == keep) {
    if (!(v > tv[c - 1])) return;
    --c;
  }
  long p = c;
  while (p > 0 && v > tv[p - 1]) { tv[p] = tv[p - 1]; ti[p] = ti[p - 1]; --p; }
  tv[p] = v;
  ti[p] = i;
  *cnt = c + 1;
}

/* idx (c of them) sorted ascending (a few dozen at most: insertion sort). */
static void sort_ascending(long* idx, long c) {
  for (long a = 1; a < c; ++a) {
    const long v = idx[a];
    long b = a;
    while (b > 0 && idx[b - 1] > v) { idx[b] = idx[b - 1]; --b; }
    idx[b] = v;
  }
}

/* idx (c of them) sorted ascending with repeats dropped; returns how many are left. */
static long sorted_unique(long* idx, long c) {
  sort_ascending(idx, c);
  long u = 0;
  for (long a = 0; a < c; ++a)
    if (u == 0 || idx[a] != idx[u - 1]) idx[u++] = idx[a];
  return u;
}

/* Rows (j, k, scenario) of the scenarios idx (c, ascending) appended to out (r rows so far);
   the new count, or -2 if more than cap. */
static long put_rows(long j, long k, const long* idx, long c, long r, long* out, long cap) {
  if (r + c > cap) return -2;
  for (long a = 0; a < c; ++a) {
    out[3 * (r + a)] = j;
    out[3 * (r + a) + 1] = k;
    out[3 * (r + a) + 2] = idx[a];
  }
  return r + c;
}

CASADI_SYMBOL_EXPORT long lfm_screen(long n, long ns, long nsc, const long* screened,
    const double* G, const double* X, const unsigned char* depends, double margin, long keep,
    long* out, long cap) {
  /* The initial scenario rows of screened constraints (screening.screen_rows): in every
     group (j, k) of G (NG, N, Ns) whose largest value is >= -margin (and has no NaN), the
     keep largest values >= -margin, the first smallest, and the first largest and smallest
     scenario of every state j depends on (depends (NG, NX)) in X (N+1, NX, Ns) at step
     k + 1; written group by group (screened order, then step), each group's scenarios
     ascending. Returns the number of rows written to out (r, 3), -1 if out of memory, -2 if
     cap is too small. */
  if (ns <= 0 || n <= 0) return 0;
  double* tv = malloc((keep + 1) * sizeof(double));
  long* ti = malloc((keep + 2 * NX + 2) * sizeof(long)); /* the group's scenarios */
  long r = -1;
  if (tv && ti && keep > 0) {
    r = 0;
    for (long a = 0; a < nsc && r >= 0; ++a) {
      const long j = screened[a];
      for (long k = 0; k < n && r >= 0; ++k) {
        const double* g = G + (j * n + k) * ns;
        double mx = -INFINITY, vmin = g[0];
        long imin = 0, cnt = 0;
        int nan = 0;
        for (long i = 0; i < ns; ++i) {
          const double v = g[i];
          nan |= v != v;
          if (v > mx) mx = v;
          if (v < vmin) { vmin = v; imin = i; }
          if (v >= -margin) top_insert(tv, ti, &cnt, keep, v, i);
        }
        if (nan || !(mx >= -margin)) continue;
        ti[cnt++] = imin;
        for (int m = 0; m < NX; ++m) {
          if (!depends[j * NX + m]) continue;
          const double* xm = X + ((k + 1) * NX + m) * ns;
          long ia = 0, ib = 0;
          for (long i = 1; i < ns; ++i) {
            if (xm[i] > xm[ia]) ia = i;
            if (xm[i] < xm[ib]) ib = i;
          }
          ti[cnt++] = ia;
          ti[cnt++] = ib;
        }
        r = put_rows(j, k, ti, sorted_unique(ti, cnt), r, out, cap);
      }
    }
  }
  free(tv);
  free(ti);
  return r;
}

CASADI_SYMBOL_EXPORT long lfm_violated(long n, long ns, long nsc, const long* screened,
    const double* S, const double* Jg, const double* G, const double* d, const double* s_pos,
    long q, const long* pos, double tol, long keep, long* out, long cap) {
  /* The rows a QP step d violates (screening.worst_rows): the linearised values
     G + Jg_k S_k d - s_pos[j, k] (s_pos (NG, N), the QP's slack of each group) of the
     screened constraints, rows pos (q, 3) excluded; in every group without NaN, the keep
     largest above tol, written group by group (screened order, then step), each group's
     scenarios ascending. Returns the number of rows written to out (r, 3), -1 if out of
     memory, -2 if cap is too small. */
  const long groups = nsc * n;
  unsigned char* nan = calloc(groups + 1, 1);
  double* tv = malloc((groups * keep + 1) * sizeof(double));
  long* ti = malloc((groups * keep + 1) * sizeof(long));
  long* cnt = calloc(groups + 1, sizeof(long));
  /* the excluded scenarios of each group, ascending, from skip[first[grp]] on, and the
     position of the next one to meet as the scenarios ascend */
  long* first = calloc(groups + 1, sizeof(long));
  long* next = malloc((groups + 1) * sizeof(long));
  long* skip = malloc((q + 1) * sizeof(long));
  long at[NGR + 1], r = -1;
  if (nan && tv && ti && cnt && first && next && skip && keep > 0) {
    for (int j = 0; j < NGR; ++j) at[j] = -1;
    for (long a = 0; a < nsc; ++a) at[screened[a]] = a;
    /* rows outside the arrays are not rows of the QP: ignored */
#define POS_GROUP(p)                                                                       \
  (pos[3 * (p)] >= 0 && pos[3 * (p)] < NGR && at[pos[3 * (p)]] >= 0 && pos[3 * (p) + 1] >= 0 \
           && pos[3 * (p) + 1] < n && pos[3 * (p) + 2] >= 0 && pos[3 * (p) + 2] < ns         \
       ? at[pos[3 * (p)]] * n + pos[3 * (p) + 1]                                            \
       : -1)
    for (long p = 0; p < q; ++p) {
      const long grp = POS_GROUP(p);
      if (grp >= 0) ++first[grp + 1];
    }
    for (long grp = 0; grp < groups; ++grp) first[grp + 1] += first[grp];
    for (long grp = 0; grp < groups; ++grp) next[grp] = first[grp];
    for (long p = 0; p < q; ++p) {
      const long grp = POS_GROUP(p);
      if (grp >= 0) skip[next[grp]++] = pos[3 * p + 2];
    }
#undef POS_GROUP
    for (long grp = 0; grp < groups; ++grp) {
      sort_ascending(skip + first[grp], first[grp + 1] - first[grp]);
      next[grp] = first[grp];
    }
    for (long k = 0; k < n; ++k)
      for (long i = 0; i < ns; ++i) {
        double sd[NXS];
        step_change(S, k, ns, i, d, sd);
        for (long a = 0; a < nsc; ++a) {
          const long j = screened[a], grp = a * n + k;
          long* cur = next + grp;
          while (*cur < first[grp + 1] && skip[*cur] < i) ++*cur;
          if (*cur < first[grp + 1] && skip[*cur] == i) continue;
          const double v = linear_value(n, ns, Jg, G, j, k, i, sd) - s_pos[j * n + k];
          if (v != v)
            nan[grp] = 1;
          else if (v > tol)
            top_insert(tv + grp * keep, ti + grp * keep, cnt + grp, keep, v, i);
        }
      }
    r = 0;
    for (long a = 0; a < nsc && r >= 0; ++a)
      for (long k = 0; k < n && r >= 0; ++k) {
        const long grp = a * n + k;
        if (nan[grp]) continue;
        long* idx = ti + grp * keep;
        r = put_rows(screened[a], k, idx, sorted_unique(idx, cnt[grp]), r, out, cap);
      }
  }
  free(nan);
  free(tv);
  free(ti);
  free(cnt);
  free(first);
  free(next);
  free(skip);
  return r;
}
