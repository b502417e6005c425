"""Mitsuba 3 texture plugin that evaluates warptex solid textures lazily at shading points."""
