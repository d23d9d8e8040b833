"""Grip-force sources other than Steerlab's own glove unit."""
