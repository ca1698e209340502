"""What every scenario shares, and nothing scenario-specific: the command-line glue (:mod:`.entry`), the
calibration a result is reported with (:mod:`.calibration`), the simulated interrogator's optics by name
(:mod:`.optics`), the three reconstruction pipelines (:mod:`.pipelines`) and time series with their EM-sensor-like
readings and viewer replay (:mod:`.series`). Scenarios import from here, never from each other."""
