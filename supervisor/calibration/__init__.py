"""Camera calibration: intrinsics from ChArUco views and the eye-in-hand transform `T_flange_cam`.

`intrinsics` (CharucoDetector + calibrateCamera), `handeye` (closed form + reprojection refinement),
`report` (the config's camera section as YAML, a JSON report, a residual plot), `commands` (what
`supervisor calibrate ...` runs).
"""
