
static casadi_real kklc_FUNCTION(casadi_real x) {
  casadi_real y;
  kklc_vFUNCTION(&x, 1, &y);
  return y;
}
