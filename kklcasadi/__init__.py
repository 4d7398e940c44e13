"""kklcasadi: learned KKL observers for controlled nonlinear systems, exported to CasADi and C."""

__version__ = "0.1.0"
