"""What a commissioner runs with the twin: the virtual measurement of an optic's transfer
functions (:mod:`.measurement`), an identification campaign that designs, injects, records
and fits until a target (:mod:`.campaign`), and a ringdown of a served optic
(:mod:`.ringdown`). What proves twind (the corpus, the rates, the benchmarks, the soak) is
:mod:`twind.lab`'s, above this."""
