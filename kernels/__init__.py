"""Warp kernels of wsim, one module per kernel family (installed as ``wsim.kernels``).

Kernels are pure functions of their arrays; the launchers in ``wsim/<method>/`` allocate,
schedule and check. Each module is one Warp module, compiled once per device on first launch.
"""
