"""A model whose module takes two minutes to import (a heavy dependency on a slow network disk): its agent is
running but registers long after a short ``--register-timeout``."""
from __future__ import annotations

import time

from .broken import _Holder

time.sleep(120.0)


class Late(_Holder):
    kind = "late"
