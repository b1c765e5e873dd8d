"""Device drivers: one small interface per kind of device (drivers.base) and its implementations."""
