"""Deliberately broken: importing this module fails, as a plugin with a missing dependency would."""

raise ImportError("mosiv_broken_plugin needs the package 'not-installed-anywhere'")
