"""clsplat.models.pgt (in progress)."""
