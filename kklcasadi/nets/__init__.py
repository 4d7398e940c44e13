"""Networks: typed specs of the blocks and their arrays (:mod:`.specs`), and the CasADi twin of
the torch networks (:mod:`.builders`: ``(spec, arrays) -> ca.Function``)."""
