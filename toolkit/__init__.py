"""dars: posed photographs of galleries -> decomposed digital twins (DARS-NeRF).

One module (or small subpackage) per SPEC stage — ``scene`` (load), ``colour``, ``segment``, ``lightnet``, ``sh``,
``edges`` (weight maps), ``priors`` (the stages on a scene), ``sampling``, ``field``, ``shading``, ``render`` /
``pipeline``, ``losses``, ``train/``, ``evaluate`` / ``metrics`` / ``report`` / ``ablation``, ``mesh/`` / ``bake`` /
``asset``, ``relight`` — and ``cli/``, the ``dars`` command. README.md maps each stage to its module.
"""
