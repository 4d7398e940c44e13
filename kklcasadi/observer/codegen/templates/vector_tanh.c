
/* tanh(a) = expm1(2a) / (expm1(2a) + 2) for a in [0, 20] or NaN (tanh(20) rounds to 1) */
static inline casadi_real KKLCV_tanh_clamped(casadi_real a) {
  casadi_real b = 2.0 * a, kd = b * KKLC_LOG2E + KKLC_SHIFTER, k = kd - KKLC_SHIFTER;
  casadi_real r = (b - k * KKLC_LN2HI) - k * KKLC_LN2LO, s = KKLCV_pow2(kd);
  casadi_real e = s * KKLCV_expm1_reduced(r) + (s - 1.0);
  return e / (e + 2.0);
}

/* y[i] = tanh(x[i]) for i < n; y is x or does not overlap it. Passes over y that vectorise. */
static void KKLCV_vtanh(const casadi_real* x, casadi_int n, casadi_real* y) {
  casadi_int i;
  if (y != x) for (i = 0; i < n; ++i) y[i] = x[i];
  for (i = 0; i < n; ++i) y[i] = y[i] > 20.0 ? 20.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = y[i] < -20.0 ? -20.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = copysign(KKLCV_tanh_clamped(fabs(y[i])), y[i]);
}
