"""Before anything is matched: the instrument's angular steps, ground removal and cropping."""
