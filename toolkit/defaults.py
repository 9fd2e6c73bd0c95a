"""Defaults that a measurement chose, kept where both the trainer and the command line read them.

Importing this module loads neither torch nor numpy (``dars --help`` imports it).
"""

from __future__ import annotations

__all__ = ["DARS_DEFAULT"]

DARS_DEFAULT = False
"""The sampler a run gets when it does not ask for one: True — DARS (W-weighted ray selection, per-ray fine budgets,
W-guided along-ray density; ``dars train --dars``); False — uniform pixels and hierarchical fine samples
(``--no-dars``). Chosen by paired DARS-vs-uniform runs at equal steps on the validation galleries, not by the sample
scene (README, "DARS vs uniform sampling"): over 9 pairs on three galleries neither beat the other beyond its seed
spread, so the simpler sampler, which also renders faster, is the default and DARS is one flag away."""
