"""Benchmarks behind `dmais bench`: each prints a table and writes CSV.

`markers` (a rendered dataset with truth) and its synthetic suites `marker_regimes`,
`marker_effects`, `marker_photos` (`marker_suites` runs them) on `marker_scenes`; `pose` (the
generalized pose solver against OpenCV, pycolmap and PoseLib, and the pose stage's throughput);
`campaign` (the workflow at flight-campaign scale). The algorithm packages never import this one.
"""
