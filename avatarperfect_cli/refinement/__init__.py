"""The refinement stages' algorithms (paper §6): visibility, pose suggestion, edits, erasing."""
