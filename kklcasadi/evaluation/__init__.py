"""Evaluation: the benchmark of docs/protocol.md (:mod:`.protocol`), its trial cache
(:mod:`.trialcache`), compiled trajectories (:mod:`.compiled`), the estimator comparison
(:mod:`.compare`), tables and plots (:mod:`.report`) and the speed benchmarks (:mod:`.bench`)."""
