"""The synthetic sample subject: procedural clothes on the anny body, posed motions, ground-truth renders."""
