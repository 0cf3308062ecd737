"""What a calibration is worth afterwards: ISO 9283 pose characteristics with their confidence intervals
(``iso9283``), the standard's test cube and poses (``cube``), and compensated targets for a controller that keeps
its own nominal model (``compensate``). Pure: numpy/scipy, SI, no I/O; procedures and the CLI call it."""
