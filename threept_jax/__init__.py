"""threept_jax: 3PT, the 3D-Object Perception Transformer, in JAX.

The library is pure: functions and ``nnx.Module``s, no I/O, flags or printing. Command-line
programs live in the sibling packages ``datagen``, ``train`` and ``infer``.
"""

__version__ = "0.1.0"
