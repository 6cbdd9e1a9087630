"""Experiments: one module per figure or table (see avsm_dr.cli)."""
