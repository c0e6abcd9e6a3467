"""mosiv-genesis: scenes simulated and rendered by the Genesis engine (scene source ``genesis``)."""
