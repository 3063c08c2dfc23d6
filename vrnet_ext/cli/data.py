"""``vrnet data``: the data sets the other commands read, made from their public releases."""
from __future__ import annotations

from vrnet_ext.cli.common import DefaultsHelpFormatter, output_folder


def add_data(sub) -> None:
    p = sub.add_parser("data", help="make the data files the other commands read (ModelNet40)",
                       description="Makes data files from public releases.", formatter_class=DefaultsHelpFormatter)
    kinds = p.add_subparsers(dest="kind", required=True)
    modelnet = kinds.add_parser(
        "modelnet40", help="modelnet40_1024_{train,test}.h5 from the modelnet40_ply_hdf5_2048 release",
        description="Writes modelnet40_1024_train.h5 and modelnet40_1024_test.h5 (what `vrnet eval` and `vrnet "
                    "train` read) from the PointNet authors' ModelNet40 release, modelnet40_ply_hdf5_2048 (its zip "
                    "archive or the folder it unpacks to: ply_data_train*.h5, ply_data_test*.h5): the first 1024 "
                    "points of each shape, the official train / test split (docs/data.md).",
        formatter_class=DefaultsHelpFormatter)
    modelnet.add_argument("source", help="modelnet40_ply_hdf5_2048.zip, or the folder holding its .h5 files")
    modelnet.add_argument("--out-dir", type=output_folder, default=None,
                          help="where to write (default: $VRNET_DATA/modelnet40, else "
                               "~/.local/share/vrnet_ext/modelnet40, where the other commands look)")


def run_data(args) -> int:
    from pathlib import Path

    from vrnet_ext.data.convert import convert_modelnet40
    from vrnet_ext.data.modelnet import written_root

    out_dir = Path(args.out_dir) if args.out_dir else written_root()
    counts = convert_modelnet40(args.source, out_dir)
    print(f"wrote {out_dir}/modelnet40_1024_train.h5 ({counts['train']} shapes) and modelnet40_1024_test.h5 "
          f"({counts['test']} shapes)")
    if args.out_dir:
        print(f"use it with --data-dir {out_dir} (or VRNET_DATA={out_dir.parent} when the folder is named modelnet40)")
    return 0
