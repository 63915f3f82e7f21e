"""A learnt hold check for camera policies: which of a policy's top picks the cell would hold, taught by
rehearsals on the cell's twin (``policies/cell_twin.py``) and judged from the observation alone."""
