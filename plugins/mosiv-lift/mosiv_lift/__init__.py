"""mosiv-lift: turn a reconstruction into simulation particles with object and material tags."""
