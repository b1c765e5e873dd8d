"""EDS files of the reference CANopen devices (package data of the CANopen driver)."""
