"""The CAN bus's side of a leg: the motor controllers' frames (ODrive CANSimple: ``odrive_can``; CubeMars/T-Motor AK
MIT mode: ``mit_can``), recording and reading logs (``can_log``), what a log holds (``log_data``), the file checks
(``log_checks``) and the logger's clock (``log_clock``)."""
