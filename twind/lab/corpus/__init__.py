"""The proof corpus of ``twind diagnose`` and the benchmark that scores it
(``twind bench --suite diagnose``).

Each case is an optic whose nominal parameters drifted at random
(:data:`~twind.commissioning.concealed.SPREAD`) and, except for the nulls, that carries one
effect of the catalogue of docs/model.md, put into the plant the twin runs *by hand*
(:mod:`twind.commissioning.hidden`): the coil or OSEM columns of the actuation and sensing
matrices, the loop delay, the coil-driver pole, the SIDE column of the face OSEMs; a wire
asymmetry is one loop's clamp raised in the geometric rigid-body model
(:func:`~twind.commissioning.hidden.raised_clamp`); bounce and roll are the geometric body's
VERT and ROLL seen by face heads whose axes tilt against the optic, in 3-D kinematics
(:func:`~twind.commissioning.hidden.tilted_heads`). Beyond the catalogue
(:data:`~.cases.BEYOND`): a small body on a spring at a face point, a new coordinate of the
mechanics in 3-D kinematics (:func:`~twind.commissioning.hidden.attached_body`); one coil
driver's or OSEM readback's own pole/zero stage, integrated by the engine as a state
(:func:`~twind.commissioning.hidden.one_stage`); and pairs of catalogue effects in one
plant. None of it goes through :mod:`twind.model.effects`, whose models the diagnosis fits
to explain it. The twin's time-domain engine measures the optic, noise through the loop, and
the measurement reaches ``diagnose`` as users have it: a diaggui XML set (like example_null)
or an MCAP session with its injection events.

Each effect is concealed: scaled so that its largest change of any bin of ``IN1/EXC`` the
fit uses is :data:`~twind.commissioning.concealed.CONCEAL_SIGMA` times that bin's standard
error, while its change summed over all bins (``present``, in chi^2 units) shows it is
there.

Scored as the issue asks: the right effect named (or declared equivalent) with its key
parameter within 35 %; nothing claimed on the nulls; chi^2/nu after augmentation against
the nulls'; seconds per case. To tell a miss's scatter from a bias, each key parameter's
error is also given in its own fit's sigma (:func:`~.scoring.key_z`).

Not in the default corpus: ``side_coupling`` (see :data:`~.cases.EFFECTS`).

The corpus's parts: its cases (:mod:`.cases`), their scoring (:mod:`.scoring`) and its
runs (:mod:`.run`). The independent physics (:mod:`twind.commissioning.hidden`) and the
concealment (:mod:`twind.commissioning.concealed`) are the demo's too.
"""

from twind.lab.corpus.cases import BEYOND, EFFECTS, Case, make_cases
from twind.lab.corpus.run import measure, run_corpus
from twind.lab.corpus.scoring import (
    AS_GOOD,
    KEY_TOLERANCE,
    RESOLVED_F,
    RESOLVED_MARGIN,
    Score,
    body_start,
    key_error,
    key_z,
    score,
    stage_error,
    summary,
)

__all__ = [
    "AS_GOOD",
    "BEYOND",
    "Case",
    "EFFECTS",
    "KEY_TOLERANCE",
    "RESOLVED_F",
    "RESOLVED_MARGIN",
    "Score",
    "body_start",
    "key_error",
    "key_z",
    "make_cases",
    "measure",
    "run_corpus",
    "score",
    "stage_error",
    "summary",
]
