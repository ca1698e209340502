"""What every scenario shares, and nothing scenario-specific: the command-line glue (:mod:`.entry`), the
calibration a result is reported with (:mod:`.calibration`) and the simulated interrogator's optics by name
(:mod:`.optics`). Scenarios import from here, never from each other."""
