"""The local planner: a 3D local map, one planner with one cost and a speed law, the safety chain
(docs/planner.md)."""
