"""The camera from its targets: the ChArUco boards and their edges (``targets``), the OpenCV
calibration per lens setting (``camera``) and the uncertainty of its focal length (``sigma``)."""
