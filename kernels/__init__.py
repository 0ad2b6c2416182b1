"""Pure JAX kernels: arrays in, arrays out.

Importable with only jax and numpy installed: no file I/O, no meshing libraries,
no printing. Each kernel is written for one instance and batched with ``vmap``
by its caller.
"""
