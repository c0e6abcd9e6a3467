"""mosiv-synth: the benchmark scene generator of MOSIV (registered as scene source ``synth``)."""
