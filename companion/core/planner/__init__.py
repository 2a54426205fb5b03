"""The local planner: a 3D local map, one planner with one cost and a speed law, the safety chain
(docs/planner.md)."""


def compile_kernels() -> None:
    """Compile the local planner's kernels now (a few seconds, once per process): a service does it at
    start-up, so that the first tick of its first flight does not wait for the compiler."""
    from companion.core.planner import localmap, way

    localmap.compile_kernels()
    way.compile_kernels()
