"""lsu batch: an archive of scan bags reprocessed on Ray, one task per bag, locally or on a cluster."""
