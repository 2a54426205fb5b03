"""The local planner: a 3D local map, one planner with one cost and a speed law, the safety chain
(docs/planner.md)."""


def compile_kernels() -> None:
    """Compile the local planner's kernels, and those of its map's input (the eroded blocks of the
    disparity), now (a few seconds, once per process): a service does it at start-up, so that the
    first frame and tick of its first flight do not wait for the compiler."""
    from companion.core import blocks
    from companion.core.planner import localmap, way

    blocks.compile_kernels()
    localmap.compile_kernels()
    way.compile_kernels()
