"""Motions as data: paths parameterised by one coordinate."""
