"""Alignment readers and phoneme inventories with their maps to the 16 visemes (paper Fig. 2)."""
