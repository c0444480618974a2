/* A small thread pool for the native kernels that tolerates a loaded machine.
 *
 * sp_parallel(n, nthreads, fn, ctx) runs fn(ctx, c) for the chunks c = 0..n-1. The caller
 * claims chunks itself and sleeping helper threads join in when they get a CPU; the caller then
 * waits only for chunks a helper has already claimed, never for a helper that has not started
 * (a fork-join team would: on a machine shared with other jobs a helper can wait milliseconds for
 * a CPU, at every parallel region). Chunks are claimed through one atomic word holding the job's
 * generation and the next chunk, so a late helper can never run a chunk of a later job. One job
 * runs at a time (calls from several Python threads are serialized). Helpers sleep on a
 * condition variable between jobs; after fork() the child starts its own helpers.
 */
#include "pool.h"

#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdint.h>

#define MAX_HELPERS 63

static pthread_mutex_t call_mu = PTHREAD_MUTEX_INITIALIZER; /* one job at a time */
static pthread_mutex_t mu = PTHREAD_MUTEX_INITIALIZER;      /* job publication */
static pthread_cond_t cv = PTHREAD_COND_INITIALIZER;
static int n_helpers = 0, atfork_done = 0;
static uint32_t job_gen = 0;
static int job_want = 0;
static sp_task job_fn = 0;
static void *job_ctx = 0;
static long job_n = 0;
static _Atomic uint64_t claim = 0; /* (generation << 32) | next chunk */
static _Atomic long done = 0;      /* chunks finished by helpers in the current job */

static int try_claim(uint32_t gen, long n, long *chunk) {
    uint64_t v = atomic_load(&claim);
    for (;;) {
        if ((uint32_t)(v >> 32) != gen) return 0;
        long c = (long)(v & 0xffffffffu);
        if (c >= n) return 0;
        if (atomic_compare_exchange_weak(&claim, &v, v + 1)) {
            *chunk = c;
            return 1;
        }
    }
}

static void *helper(void *arg) {
    int idx = (int)(intptr_t)arg;
    uint32_t seen = 0;
    pthread_mutex_lock(&mu);
    seen = job_gen;
    for (;;) {
        while (job_gen == seen) pthread_cond_wait(&cv, &mu);
        seen = job_gen;
        if (idx >= job_want) continue; /* not wanted for this job */
        sp_task fn = job_fn;
        void *ctx = job_ctx;
        long n = job_n;
        uint32_t gen = job_gen;
        pthread_mutex_unlock(&mu);
        long c;
        while (try_claim(gen, n, &c)) {
            fn(ctx, c);
            atomic_fetch_add(&done, 1);
        }
        pthread_mutex_lock(&mu);
    }
    return 0;
}

static void after_fork_child(void) { /* the helpers do not exist in the child */
    pthread_mutex_init(&call_mu, 0);
    pthread_mutex_init(&mu, 0);
    pthread_cond_init(&cv, 0);
    n_helpers = 0;
}

static void start_helpers(int want) {
    if (!atfork_done) {
        pthread_atfork(0, 0, after_fork_child);
        atfork_done = 1;
    }
    while (n_helpers < want && n_helpers < MAX_HELPERS) {
        pthread_t t;
        pthread_attr_t at;
        pthread_attr_init(&at);
        pthread_attr_setdetachstate(&at, PTHREAD_CREATE_DETACHED);
        int rc = pthread_create(&t, &at, helper, (void *)(intptr_t)n_helpers);
        pthread_attr_destroy(&at);
        if (rc != 0) break;
        ++n_helpers;
    }
}

void sp_parallel(long n, int nthreads, sp_task fn, void *ctx) {
    if (nthreads <= 1 || n <= 1) {
        for (long c = 0; c < n; ++c) fn(ctx, c);
        return;
    }
    pthread_mutex_lock(&call_mu);
    pthread_mutex_lock(&mu);
    start_helpers(nthreads - 1);
    uint32_t gen = ++job_gen;
    job_fn = fn;
    job_ctx = ctx;
    job_n = n;
    job_want = nthreads - 1;
    atomic_store(&done, 0);
    atomic_store(&claim, (uint64_t)gen << 32);
    pthread_cond_broadcast(&cv);
    pthread_mutex_unlock(&mu);
    long c, mine = 0;
    while (try_claim(gen, n, &c)) {
        fn(ctx, c);
        ++mine;
    }
    for (int spin = 0; atomic_load(&done) + mine < n; ++spin) /* chunks helpers are running */
        if (spin > 64) sched_yield();
    pthread_mutex_unlock(&call_mu);
}
