
/* kklcasadi: with gcc or clang on x86 the kernels below also come in an AVX2 version (gcc
 * vector extensions; the same results bit for bit, as long as no FMA contraction), used where
 * the CPU has AVX2: always when the build targets it (-march=native on a recent CPU), else
 * as __builtin_cpu_supports finds at run time. -DKKLC_NO_DISPATCH compiles the portable C99
 * version only. */
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__)) \
    && !defined(KKLC_NO_DISPATCH)
#define KKLC_DISPATCH 1
typedef double kklc_v4 __attribute__((vector_size(32)));
#ifdef KKLC_FUSED
/* the mat-vec kernels' AVX2 version sums with fused multiply-adds (not bitwise): it needs FMA too */
#include <immintrin.h>
#define kklc_fma4(a, b, c) ((kklc_v4) _mm256_fmadd_pd((__m256d) (a), (__m256d) (b), (__m256d) (c)))
#if defined(__AVX2__) && defined(__FMA__)
#define KKLC_AVX2
#define KKLC_HAS_AVX2 1
#else
#define KKLC_AVX2 __attribute__((target("avx2,fma")))
#define KKLC_HAS_AVX2 (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
#endif
#else
#ifdef __AVX2__
#define KKLC_AVX2
#define KKLC_HAS_AVX2 1
#else
#define KKLC_AVX2 __attribute__((target("avx2")))
#define KKLC_HAS_AVX2 __builtin_cpu_supports("avx2")
#endif
#endif
#endif
