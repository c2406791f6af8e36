"""Benchmarks behind `dmais bench`: each prints a table and writes CSV.

`markers` (a rendered dataset with truth) and its synthetic suites `marker_regimes`,
`marker_effects`, `marker_photos`, `marker_texture` (`marker_suites` runs them) on `marker_scenes`;
`periodic` (identification on OpenCV's chessboard photographs); `pose` (the generalized pose solver
against OpenCV, pycolmap and PoseLib, the fallback, and the pose stage's throughput); `pose_hard`
(the narrow regimes against a multi-start reference); `campaign` (the workflow at flight-campaign
scale); `sigma` (poses.csv's 1-sigma against the truth); `mounting` (pose.mounting's in-flight rig
against the truth). The algorithm packages never import this one.
"""
