/* example.c: the exported controller on the command line (built by the Makefile).

     example PROBLEM.txt             the plan for one scenario problem: PROBLEM.txt holds
                                     whitespace-separated numbers, x0 (LFM_NX) then W (LFM_NS
                                     x LFM_N x LFM_NW: scenario-major, then step, then force
                                     component); prints LFM_N lines of LFM_NU numbers
     example --steps MEASUREMENTS.txt
                                     the controller's whole step on each measurement (rows of
                                     LFM_NX numbers), from a reset with seed 0; prints one line
                                     of LFM_NU numbers per step
     --time K                        (either mode) repeats it K times (1 <= K <= 1000000)
                                     and prints the median and 95th percentile of one solve
                                     or step in microseconds to stderr: "time_us median p95"
   A problem that is not solved prints nothing on stdout (its status on stderr); a step
   prints the input it applies, the fallback input for a measurement with a NaN or infinite
   number. Exit status 0 on success, 1 when a solve did not succeed, 2 on bad arguments or
   input (a NaN or infinite number in a problem). */
#include <errno.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "lfm_controller.h"

#define MAX_REPEATS 1000000L /* --time K at most */

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static int compare(const void* a, const void* b) {
  const double x = *(const double*)a, y = *(const double*)b;
  return (x > y) - (x < y);
}

static void report_time(double* t, long k) {
  qsort(t, (size_t)k, sizeof(double), compare);
  long p95 = (long)(0.95 * (double)(k - 1) + 0.5);
  fprintf(stderr, "time_us %.3f %.3f\n", 1e6 * t[(k - 1) / 2] * 0.5 + 1e6 * t[k / 2] * 0.5,
          1e6 * t[p95]);
}

/* Reads count numbers from f into out; 0 on success. */
static int read_numbers(FILE* f, double* out, long count) {
  for (long i = 0; i < count; ++i)
    if (fscanf(f, "%lf", out + i) != 1) return 1;
  return 0;
}

static void print_row(const double* v, int n) {
  for (int q = 0; q < n; ++q) printf(q ? " %.17g" : "%.17g", v[q]);
  printf("\n");
}

static int run_problem(lfm_controller* c, FILE* f, long repeats) {
  static double x0[LFM_NX], W[(long)LFM_NS * LFM_N * LFM_NW], plan[LFM_N * LFM_NU];
  double extra;
  if (read_numbers(f, x0, LFM_NX) || read_numbers(f, W, (long)LFM_NS * LFM_N * LFM_NW)) {
    fprintf(stderr, "example: expected %d + %ld numbers (x0, then W)\n", LFM_NX,
            (long)LFM_NS * LFM_N * LFM_NW);
    return 2;
  }
  if (fscanf(f, "%lf", &extra) == 1) {
    fprintf(stderr, "example: more numbers than x0 and W\n");
    return 2;
  }
  double* t = malloc(sizeof(double) * (size_t)(repeats > 0 ? repeats : 1));
  if (!t) {
    fprintf(stderr, "example: out of memory\n");
    return 2;
  }
  int status = 0;
  for (long r = 0; r < (repeats > 0 ? repeats : 1); ++r) {
    lfm_controller_reset(c, 0);
    const double t0 = now();
    status = lfm_controller_solve(c, x0, W, plan);
    t[r] = now() - t0;
  }
  if (repeats > 0) report_time(t, repeats);
  free(t);
  if (status == LFM_BAD_INPUT) {
    fprintf(stderr, "example: %s: a NaN or infinite number in x0 or W\n", lfm_status_name(status));
    return 2;
  }
  if (status != LFM_SOLVED && status != LFM_ACCEPTABLE) { /* no plan on stdout */
    fprintf(stderr, "example: %s\n", lfm_status_name(status));
    return 1;
  }
  for (int k = 0; k < LFM_N; ++k) print_row(plan + k * LFM_NU, LFM_NU);
  return 0;
}

static int run_steps(lfm_controller* c, FILE* f, long repeats) {
  long rows = 0, cap = 64;
  double* y = malloc(sizeof(double) * LFM_NX * (size_t)cap);
  while (y && !read_numbers(f, y + rows * LFM_NX, LFM_NX)) {
    if (++rows == cap) {
      cap *= 2;
      double* bigger = realloc(y, sizeof(double) * LFM_NX * (size_t)cap);
      if (!bigger) break;
      y = bigger;
    }
  }
  if (!y || rows == 0) {
    fprintf(stderr, "example: no measurements (rows of %d numbers)\n", LFM_NX);
    free(y);
    return 2;
  }
  const long passes = repeats > 0 ? repeats : 1;
  /* (passes <= MAX_REPEATS: the product below fits; a size too large fails malloc) */
  if ((size_t)rows > SIZE_MAX / sizeof(double) / (size_t)passes) {
    fprintf(stderr, "example: --time %ld times %ld measurements is too many\n", passes, rows);
    free(y);
    return 2;
  }
  double* t = malloc(sizeof(double) * (size_t)passes * (size_t)rows);
  double* u = malloc(sizeof(double) * LFM_NU * (size_t)rows);
  if (!t || !u) {
    fprintf(stderr, "example: out of memory\n");
    free(y), free(t), free(u);
    return 2;
  }
  int status = 0, failed = 0;
  for (long p = 0; p < passes; ++p) {
    lfm_controller_reset(c, 0);
    for (long k = 0; k < rows; ++k) {
      const double t0 = now();
      status = lfm_controller_step(c, y + k * LFM_NX, u + k * LFM_NU);
      t[p * rows + k] = now() - t0;
      if (status == LFM_NO_STEP) {
        fprintf(stderr, "example: this agent's estimator is not exported (use a problem)\n");
        free(y), free(t), free(u);
        return 2;
      }
      failed |= status != LFM_SOLVED && status != LFM_ACCEPTABLE;
    }
  }
  if (repeats > 0) report_time(t, passes * rows);
  for (long k = 0; k < rows; ++k) print_row(u + k * LFM_NU, LFM_NU);
  free(y), free(t), free(u);
  return failed ? 1 : 0;
}

int main(int argc, char** argv) {
  long repeats = 0;
  int steps = 0;
  const char* path = NULL;
  for (int a = 1; a < argc; ++a) {
    if (!strcmp(argv[a], "--time") && a + 1 < argc) {
      const char* text = argv[++a];
      char* end = NULL;
      errno = 0;
      repeats = strtol(text, &end, 10);
      if (errno || end == text || *end || repeats < 1 || repeats > MAX_REPEATS) {
        fprintf(stderr, "example: --time %s: must be a whole number from 1 to %ld\n", text,
                MAX_REPEATS);
        return 2;
      }
    } else if (!strcmp(argv[a], "--steps"))
      steps = 1;
    else if (argv[a][0] == '-' && argv[a][1])
      path = NULL, a = argc;
    else
      path = argv[a];
  }
  if (!path) {
    fprintf(stderr, "usage: %s [--time K] PROBLEM.txt | %s [--time K] --steps MEASUREMENTS.txt\n",
            argv[0], argv[0]);
    return 2;
  }
  FILE* f = strcmp(path, "-") ? fopen(path, "r") : stdin;
  if (!f) {
    perror(path);
    return 2;
  }
  lfm_controller* c = lfm_controller_new();
  if (!c) {
    fprintf(stderr, "example: out of memory\n");
    return 2;
  }
  const int code = steps ? run_steps(c, f, repeats) : run_problem(c, f, repeats);
  lfm_controller_free(c);
  if (f != stdin) fclose(f);
  return code;
}
