/* The compiled SQP loop's interface (sqp.c): its options, its problem and its entry points.
   Included by sqp.c, and by the exported controller (controllers/export), which calls the
   loop from its own translation unit. */
#ifndef LFM_SQP_H
#define LFM_SQP_H

/* FastSolverOptions, one field each (bools and choices as longs). */
typedef struct {
  long max_iter;
  double tol, acceptable_tol;
  long acceptable_iter;
  double step_tol, final_step_tol, screen_margin;
  long screen_rows;
  double add_tol;
  long max_qp_rounds;
  double armijo, backtrack, min_step, hessian_floor, slack_regularisation;
  long second_order_correction;
  double soc_below_ratio, damping_init, damping_threshold, damping_decrease;
  long hessian_modification; /* 0 "floor", 1 "abs", 2 "augmented" */
  long elastic_on_demand;    /* elastic_qp == "on_demand" */
  long max_expand;
  double expand_ratio;
  long restart_mirror, restart_straight; /* "mirror", "straight" in restarts */
  double restart_threshold;
  long restart_probe;
  double restart_optimism, restart_margin, restart_same_tol, restart_near_tol;
  double trust_radius, min_trust_radius;
  long threads;
  double max_time; /* [s] per solve; INFINITY: none */
} lfm_sqp_options;

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
  const unsigned char* depends;               /* (NG, NX) constraint j depends on state m */
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

#endif
