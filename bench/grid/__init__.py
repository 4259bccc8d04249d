"""What a cell is: the cell-kind table, cells and their ids, the protocol and the profiles, grid files."""
