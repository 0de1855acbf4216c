"""Taking a trained scene out of egobench: the INRIA 3DGS PLY (`ply`) and a fly-through video (`video`)."""
