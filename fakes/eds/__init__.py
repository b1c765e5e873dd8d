"""EDS files of the simulated CANopen nodes (the fake's own copies; fakes never import drivers)."""
