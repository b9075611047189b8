"""What a commissioner runs with the twin: the virtual measurement of an optic's transfer
functions (:mod:`.measurement`), an identification campaign that designs, injects, records
and fits until a target (:mod:`.campaign`), a ringdown of a served optic (:mod:`.ringdown`),
and the demo (:mod:`.demo`): an optic with physics the model left out, put into its plant
by hand (:mod:`.hidden`) and concealed in its measurement (:mod:`.concealed`), diagnosed
beside the nominal one. What proves twind (the corpus, the rates, the benchmarks, the soak)
is :mod:`twind.lab`'s, above this."""
