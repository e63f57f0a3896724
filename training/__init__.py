"""twomass-som: identification of two-mass drive mechanics (features, maps, CLI)."""
