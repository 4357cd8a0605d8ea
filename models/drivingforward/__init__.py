"""clsplat.models.drivingforward (in progress)."""
