"""The Warp kernels of ``warp_worlds.WarpWorlds.play``: controls read tick by tick on the device.

A module of its own because Warp reads a kernel's annotations as types (no
``from __future__ import annotations`` here) and imports ``warp`` at the top: import it only
where MuJoCo Warp is installed (``warp_worlds`` does so lazily).
"""

import warp as wp


@wp.kernel(enable_backward=False)
def tick_controls(sequence: wp.array3d(dtype=wp.float32),   # (T, N, nu) a control sequence
                  tick: wp.array(dtype=wp.int32),            # (1,) the tick to read (the last one past the end)
                  ctrl: wp.array2d(dtype=wp.float32)):       # (N, nu) the worlds' controls
    world, actuator = wp.tid()
    ctrl[world, actuator] = sequence[wp.min(tick[0], sequence.shape[0] - 1), world, actuator]


@wp.kernel(enable_backward=False)
def next_tick(tick: wp.array(dtype=wp.int32)):               # (1,)
    tick[0] = tick[0] + 1
