"""The canonical structure table: `vert_labels` values mean the same thing whatever source a mesh came from."""

# Structure name -> id (the dataset's `vert_labels`); 0 = unlabelled.
STRUCTURES: dict[str, int] = {"lv": 1, "myo": 2, "rv": 3, "la": 4, "ra": 5, "aorta": 6, "pa": 7}
