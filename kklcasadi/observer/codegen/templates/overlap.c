
/* kklcasadi: whether the arrays a[0..na-1] and b[0..nb-1] share memory */
static int kklc_overlap(const casadi_real* a, casadi_int na, const casadi_real* b, casadi_int nb) {
  uintptr_t a0 = (uintptr_t) a, b0 = (uintptr_t) b;
  return a0 < b0 + (uintptr_t) nb * sizeof(casadi_real)
      && b0 < a0 + (uintptr_t) na * sizeof(casadi_real);
}
