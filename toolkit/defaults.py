"""Defaults that a measurement chose, kept where both the trainer and the command line read them.

Importing this module loads neither torch nor numpy (``dars --help`` imports it).
"""

from __future__ import annotations

__all__ = ["DARS_DEFAULT", "SNAP_LAYOUT_DEFAULT", "YAW_FROM_DEFAULT"]

DARS_DEFAULT = False
"""The sampler a run gets when it does not ask for one: True — DARS (W-weighted ray selection, per-ray fine budgets,
W-guided along-ray density; ``dars train --dars``); False — uniform pixels and hierarchical fine samples
(``--no-dars``). Chosen by paired DARS-vs-uniform runs at equal steps on the validation galleries, not by the sample
scene (README, "DARS vs uniform sampling"): over 9 pairs on three galleries neither beat the other beyond its seed
spread, so the simpler sampler, which also renders faster, is the default and DARS is one flag away."""

SNAP_LAYOUT_DEFAULT = 0.075
""":attr:`toolkit.asset.AssetConfig.snap_layout` (``dars export-asset --snap-layout``): the tolerance, as a fraction of
the median depth of the mesh's depth maps, within which a vertex the field labels wall or floor moves onto a
confident face of the run's room box. 3 times the fused mesh's median relative depth error (2.4 % on validation
gallery 1000002). The gain is flat around it: the mesh's median depth error at 0.05 / 0.075 / 0.1 / 0.125 was
1.71 / 1.67 / 1.65 / 1.64 cm on 1000002 (7.60 unsnapped) and 2.67 / 2.62 / 2.59 / 2.59 cm on the bundled sample
without its ``aabb`` (5.48), every vertex movable (README, "Walls and floor flattened onto the room's box"). Since
2026-12-05 the simplified mesh is snapped (before, the full-resolution one, which the simplifier then tore: README,
"The GLB flattened after its simplification")."""

YAW_FROM_DEFAULT = "lines"
""":attr:`toolkit.layout.LayoutConfig.yaw_from` (``dars priors layout --yaw-from``): where the room box's walls get
their directions — ``"lines"``, the photos' straight edges (falling back to the sparse points without a clear peak),
or ``"points"``, the sparse points' histograms. Chosen on 2026-12-05 against the generator's walls (scoring only):
within 0.17° over the eight validation galleries at four turns of the world each, where the points were up to 2.4°
off (README, "The room's yaw from the photos' edges")."""
