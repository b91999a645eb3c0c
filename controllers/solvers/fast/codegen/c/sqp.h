/* The compiled SQP loop's interface (sqp.c): its options, its problem and its entry points.
   Included by sqp.c, and by the exported controller (controllers/export), which calls the
   loop from its own translation unit. */
#ifndef LFM_SQP_H
#define LFM_SQP_H

#include "sqp_interface.h" /* lfm_sqp_options, the statuses SQ_*, the statistics ST_* */

/* The scenario problem (controllers/problem.py) and what the solver finds in it. */
typedef struct {
  long n, ns;                                 /* horizon N, scenarios Ns */
  double slack_penalty;                       /* rho */
  const double *input_lower, *input_upper;    /* (NU) */
  const double *goal, *Q, *Qf, *R;            /* (NX), (NX, NX), (NX, NX), (NU, NU) */
  long n_shared;                              /* constraints that are one row per step */
  const long* shared;                         /* (n_shared) their indices */
  const double* shared_rows;                  /* (n_shared, N, N NU) their rows */
  long n_screened;                            /* the others */
  const long* screened;                       /* (n_screened) ascending */
  const unsigned char* depends;               /* (NG, NX) row type j depends on state m */
  long n_mirror;                              /* system.mirror_inputs */
  const long* mirror;
} lfm_sqp_problem;

typedef struct lfm_sqp lfm_sqp;

/* A solver for the problem p with the options o (both copied); NULL if out of memory. */
lfm_sqp* lfm_sqp_new(const lfm_sqp_problem* p, const lfm_sqp_options* o);
void lfm_sqp_free(lfm_sqp* s);
/* Forget the warm start: the next solve without a guess starts from zero inputs. */
void lfm_sqp_reset(lfm_sqp* s);
/* The wall-clock limit [s] of the next solves (options.max_time; INFINITY: none). */
void lfm_sqp_set_max_time(lfm_sqp* s, double max_time);
/* One solve: x0 (Ns, NX), W (Ns, N, NW), u_guess (N NU) or NULL (the last plan shifted by
   one step, zeros at first), backoff (N, NG) or NULL; out: the plan u_out (N NU), the
   predicted states X_out (N + 1, NX, Ns) or NULL, statistics stats_out (lfm_sqp_stats_count()
   values). Returns the status: 0 solved, 1 solved to an acceptable level, else why not
   (the names of controllers/solvers/fast/compiled.py STATUSES). */
int lfm_sqp_solve(lfm_sqp* s, const double* x0, const double* W, const double* u_guess,
                  const double* backoff, double* u_out, double* X_out, double* stats_out);
long lfm_sqp_stats_count(void);
/* Option name (a field of lfm_sqp_options) to value from the next solve on: 0, or -1 for an
   unknown name. */
int lfm_sqp_set_option(lfm_sqp* s, const char* name, double value);
/* A library of a feedback prediction (lfm_sqp_feedback() == 1; controllers/problem.py): the
   decision u is the nominal inputs v, each scenario applies v_k + K_k (x_k - r_k), u_guess is
   the reference plan of the law (see feedback.c). lfm_sqp_set_law gives the next solve's law
   (K (N, NU, NX) with K_0 = 0, r (N, NX)); lfm_sqp_law returns the last solve's law and its
   plan's nominal inputs (N NU; any pointer may be NULL). The problem's depends then has
   NG + 2 NU rows (the input rows depend on no state), its screened rows all of them. */
long lfm_sqp_feedback(void);
/* The model's Euler step of ns points (states xT (NX, ns), forces W (NW, ns)) under the input
   u (NU): X (2, NX, ns) the points, then their next states. 0, or 1. */
int lfm_step_points(long ns, const double* xT, const double* W, const double* u, double* X);
int lfm_sqp_set_law(lfm_sqp* s, const double* K, const double* r);
int lfm_sqp_law(const lfm_sqp* s, double* K, double* r, double* nominal);
long lfm_sqp_status_count(void);
long lfm_sqp_options_size(void); /* sizeof(lfm_sqp_options) */

#endif
