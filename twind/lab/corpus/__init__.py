"""The proof corpus of ``twind diagnose`` and the benchmark that scores it
(``twind bench --suite diagnose``).

Each case is an optic whose nominal parameters drifted at random (:data:`SPREAD`) and,
except for the nulls, that carries one effect of the catalogue of docs/model.md, put into the plant
the twin runs *by hand here*: the coil or OSEM columns of the actuation and sensing
matrices, the loop delay, the coil-driver pole, the SIDE column of the face OSEMs; a wire
asymmetry is one loop's clamp raised in the geometric rigid-body model (:func:`raised_clamp`);
bounce and roll are the geometric body's VERT and ROLL seen by face heads whose axes tilt
against the optic, in 3-D kinematics (:func:`tilted_heads`).
Beyond the catalogue (:data:`BEYOND`): a small body on a spring at a face point, a new
coordinate of the mechanics in 3-D kinematics (:func:`attached_body`); one coil driver's or
OSEM readback's own pole/zero stage, integrated by the engine as a state
(:func:`one_stage`); and pairs of catalogue effects in one plant.
None of it goes through :mod:`twind.model.effects`, whose models the diagnosis fits to
explain it.
The twin's time-domain engine measures the optic, noise through the loop, and the
measurement reaches ``diagnose`` as users have it: a diaggui XML set (like example_null) or
an MCAP session with its injection events.

Each effect is concealed: scaled so that its largest change of any bin of ``IN1/EXC`` the
fit uses is :data:`CONCEAL_SIGMA` times that bin's standard error, while its change summed
over all bins (``present``, in chi^2 units) shows it is there.

Scored as the issue asks: the right effect named (or declared equivalent) with its key
parameter within 35 %; nothing claimed on the nulls; chi^2/nu after augmentation against
the nulls'; seconds per case. To tell a miss's scatter from a bias, each key parameter's
error is also given in its own fit's sigma (:func:`key_z`).

Not in the default corpus: ``side_coupling`` (see :data:`EFFECTS`).

The corpus's parts: its independent physics (:mod:`.physics`), its cases (:mod:`.cases`),
their scoring (:mod:`.scoring`), and the runs and the demo (:mod:`.run`).
"""

from twind.lab.corpus.cases import (
    AVERAGES,
    BEYOND,
    CONCEAL_SIGMA,
    EFFECTS,
    EXCITED,
    RMS,
    ROUTE_BW,
    SPREAD,
    STOP_HZ,
    Case,
    conceal,
    drifted,
    make_cases,
    reference_data,
)
from twind.lab.corpus.physics import (
    FACES,
    MADE,
    attached_body,
    hidden,
    one_stage,
    raised_clamp,
    tilted_heads,
)
from twind.lab.corpus.run import (
    measure,
    run_corpus,
    run_demo,
)
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
    "AVERAGES",
    "BEYOND",
    "CONCEAL_SIGMA",
    "Case",
    "EFFECTS",
    "EXCITED",
    "FACES",
    "KEY_TOLERANCE",
    "MADE",
    "RESOLVED_F",
    "RESOLVED_MARGIN",
    "RMS",
    "ROUTE_BW",
    "SPREAD",
    "STOP_HZ",
    "Score",
    "attached_body",
    "body_start",
    "conceal",
    "drifted",
    "hidden",
    "key_error",
    "key_z",
    "make_cases",
    "measure",
    "one_stage",
    "raised_clamp",
    "reference_data",
    "run_corpus",
    "run_demo",
    "score",
    "stage_error",
    "summary",
    "tilted_heads",
]
