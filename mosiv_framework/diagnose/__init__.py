"""Finding missing physics (docs/DIAGNOSIS.md, docs/ARCHITECTURE.md): ``mosiv diagnose RUN``.

One module per step: ``context`` (the loaded run), ``locate`` with ``changepoint`` (where the
model misses, against a noise floor estimated from the data), ``candidates`` and
``hypothesise`` (which registered effects could explain it), ``model`` (refit with each),
``interval`` (the accepted coefficient's uncertainty), ``decide`` (held-out and
information-criterion evidence), ``report`` (diagnosis.json / diagnosis.md), ``suite``
(scores the whole chain on generated scenes with concealed effects) and ``replay`` (re-decides
a finished suite under another acceptance rule, from the saved error tables).
"""

from mosiv_framework.diagnose.budget import BUDGETS, Budget
from mosiv_framework.diagnose.diagnosis import diagnose_run, split_frames

__all__ = ["BUDGETS", "Budget", "diagnose_run", "split_frames"]
