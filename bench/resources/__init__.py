"""What a cell reads, lent by the workspace: released policies (tiny, pinned or the hub's), feature
stores (the file format, extraction runtimes), users' own policies and datasets."""
