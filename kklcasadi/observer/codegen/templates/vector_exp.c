
/* exp(x) for x in [-746, 710] or NaN: 2^k split in two factors that stay normal numbers */
static inline casadi_real KKLCV_exp_clamped(casadi_real x) {
  casadi_real kd = x * KKLC_LOG2E + KKLC_SHIFTER, k = kd - KKLC_SHIFTER;
  casadi_real r = (x - k * KKLC_LN2HI) - k * KKLC_LN2LO;
  casadi_real hd = k * 0.5 + KKLC_SHIFTER, h = hd - KKLC_SHIFTER;
  return (1.0 + KKLCV_expm1_reduced(r)) * KKLCV_pow2(hd) * KKLCV_pow2((k - h) + KKLC_SHIFTER);
}

/* y[i] = exp(x[i]) for i < n; y is x or does not overlap it. Passes over y that vectorise. */
static void KKLCV_vexp(const casadi_real* x, casadi_int n, casadi_real* y) {
  casadi_int i;
  if (y != x) for (i = 0; i < n; ++i) y[i] = x[i];
  for (i = 0; i < n; ++i) y[i] = y[i] > 710.0 ? 710.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = y[i] < -746.0 ? -746.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = KKLCV_exp_clamped(y[i]);
}
