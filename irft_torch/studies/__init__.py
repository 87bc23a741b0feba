"""Studies built on the library: the calibration harness (``studies.calibration``)."""
