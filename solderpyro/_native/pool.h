/* Thread pool of the native kernels (pool.c). */
#ifndef SP_POOL_H
#define SP_POOL_H

typedef void (*sp_task)(void *ctx, long chunk);

/* fn(ctx, c) for c = 0..n-1 on up to nthreads threads (the caller's included). */
void sp_parallel(long n, int nthreads, sp_task fn, void *ctx);

#endif
