
/* kklcasadi: exp and tanh as C99 arithmetic without branches or library calls, so that loops
 * over them vectorise. Range reduction x = k ln2 + r (|r| <= ln2/2, Cody-Waite), Taylor
 * polynomial of expm1(r) to degree 13, 2^k assembled from the exponent bits. Relative error
 * within 1 ulp (exp) and 3 ulp (tanh) of a correctly rounded result; NaN and infinities as the
 * C library; exp overflows to HUGE_VAL and underflows through the subnormals to 0. */
#define KKLC_SHIFTER 6755399441055744.0         /* 0x1.8p52: x + it rounds x to an integer */
#define KKLC_LOG2E 1.4426950408889634
#define KKLC_LN2HI 6.93147180369123816490e-01   /* ln 2 = LN2HI + LN2LO, k LN2HI exact */
#define KKLC_LN2LO 1.90821492927058770002e-10
/* a * b + c, two roundings; the AVX2 version of the evaluation path's kernels writes fma(a, b, c) instead */
#define KKLC_MADD(a, b, c) ((a) * (b) + (c))
