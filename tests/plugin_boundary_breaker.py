"""A guidance plug-in that reaches for the truth side: refused at load (tests/test_plugins.py)."""

import models.lander  # noqa: F401 - the point of this module

from gnc.guidance import ZemZevGuidance


class Peeker(ZemZevGuidance):
    pass
