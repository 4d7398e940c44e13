
/* expm1(r) for |r| <= 0.35: Taylor polynomial to degree 13 (truncation below 1e-18) */
static inline casadi_real KKLCV_expm1_reduced(casadi_real r) {
  casadi_real q = 1.0 / 6227020800.0;
  q = KKLC_MADD(q, r, 1.0 / 479001600.0);
  q = KKLC_MADD(q, r, 1.0 / 39916800.0);
  q = KKLC_MADD(q, r, 1.0 / 3628800.0);
  q = KKLC_MADD(q, r, 1.0 / 362880.0);
  q = KKLC_MADD(q, r, 1.0 / 40320.0);
  q = KKLC_MADD(q, r, 1.0 / 5040.0);
  q = KKLC_MADD(q, r, 1.0 / 720.0);
  q = KKLC_MADD(q, r, 1.0 / 120.0);
  q = KKLC_MADD(q, r, 1.0 / 24.0);
  q = KKLC_MADD(q, r, 1.0 / 6.0);
  q = KKLC_MADD(q, r, 0.5);
  return KKLC_MADD(r * r, q, r);
}

/* 2^k for an integer -1022 <= k <= 1023 held as kd = k + 0x1.8p52 */
static inline casadi_real KKLCV_pow2(casadi_real kd) {
  uint64_t bits;
  casadi_real scale;
  memcpy(&bits, &kd, sizeof bits);
  bits = (bits + 1023) << 52;
  memcpy(&scale, &bits, sizeof scale);
  return scale;
}
