"""The plant side: CasADi systems, input signals, simulation, RK4, the latent design, the
input-window convention and the training data drawn from them (Phase-1 labels, Phase-2 samples, the
``bank``'s operational runs).

Modules: :mod:`.systems`, :mod:`.signals`, :mod:`.simulate`, :mod:`.rk4`, :mod:`.design`,
:mod:`.windows`, :mod:`.data`, :mod:`.runs`.
"""
