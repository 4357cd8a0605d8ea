"""clsplat.models.autosplat (in progress)."""
