"""Studies that reproduce the seed papers: support stiffness, kv sweep (seed 004), feed sweep (seed 000)."""
