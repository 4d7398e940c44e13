"""Model files and the table of observer variants: :mod:`.files` (``weights.npz`` + ``card.json``),
:mod:`.variants` (one module per variant), :mod:`.shipped` (the models that ship with kklcasadi), :mod:`.monitor`
(the decoder-input domain monitor), :mod:`.operational` (a ``bank`` decoder's samples of its runs, no torch)."""
