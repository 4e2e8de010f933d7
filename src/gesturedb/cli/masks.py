"""`gesturedb masks DB.h5 list|add NAME EXPR [NAME EXPR ...]|remove NAME|controls`: saved control masks."""
from __future__ import annotations

import gesturedb
from gesturedb import control as masks
from gesturedb.errors import GestureDBError, ParameterError, echo_list


def add_parser(sub) -> None:
    p = sub.add_parser("masks", help="list, save or remove control masks; recompute control features",
                       description="Masks restrict the search to database frames that satisfy an expression over "
                       "the control features, e.g. 'left_wrist_height > p85 and not left_wrist_fast' "
                       "(`gesturedb masks DB.h5 list` shows the names there are).")
    p.add_argument("db", metavar="DB.h5")
    ops = p.add_subparsers(dest="op", metavar="OP", required=True)
    ops.add_parser("list", help="control features, built-in mask names and saved masks with their definitions")
    a = ops.add_parser("add", help="save mask expressions under names (several in one edit)")
    a.add_argument("pairs", nargs="*", metavar="NAME EXPR",
                   help="a name and its expression, repeated for more masks (each expression in quotes)")
    a.add_argument("--from", dest="from_file", metavar="FILE", default=None,
                   help="also save the masks of FILE (one 'NAME = EXPR' per line, '#' comments), in the same edit")
    a.add_argument("--replace", action="store_true")
    r = ops.add_parser("remove", help="delete a saved mask")
    r.add_argument("name")
    ops.add_parser("controls", help="recompute the control features from the stored joint positions")
    p.set_defaults(run=run)


def run(args) -> int:
    import numpy as np

    from gesturedb.db import edit as dbedit

    if args.op == "add":
        if len(args.pairs) % 2:
            raise ParameterError(f"add: expected NAME EXPR pairs, got {len(args.pairs)} argument(s): "
                                 f"{echo_list(args.pairs, quote=True)} (quote each expression)")
        items = list(zip(args.pairs[::2], args.pairs[1::2]))
        items += dbedit.read_mask_file(args.from_file) if args.from_file else []
        if not items:
            raise ParameterError("add: expected NAME EXPR or --from FILE, got neither")
        for name, res in dbedit.save_masks(args.db, items, replace=args.replace).items():
            print(f"saved {name}: {res.describe()}")
    elif args.op == "remove":
        dbedit.remove_mask(args.db, args.name)
        print(f"removed {args.name}")
    elif args.op == "controls":
        names = dbedit.add_control_features(args.db)
        print(f"control features: {', '.join(names)}")
    else:
        with gesturedb.open(args.db) as db:
            print(f"control features of {db.path} ({db.n_frames} frames):")
            for k, v in db.controls.items():
                p15, p50, p85 = (float(x) for x in np.percentile(v, [15, 50, 85]))
                print(f"  {k:<22} [{db.control_units[k]:>3}]  p15 {p15:8.3f}  p50 {p50:8.3f}  p85 {p85:8.3f}")
            saved = db.masks
            builtin = {k: v for k, v in masks.DEFAULT_NAMED.items() if k not in saved}
            if db.controls:
                print("built-in names (usable in any expression):")
                for k, expr in builtin.items():
                    try:
                        n = int(masks.count_bits(masks.compile_mask(expr, controls=db.controls, named=saved).words))
                        share = f"{100 * n / db.n_frames:5.1f}%"
                    except GestureDBError:  # a database without that control feature
                        share = "    -"
                    print(f"  {k:<28} {share}  {expr}")
            print("masks in the database (the <feature>_high/_low percentile masks and those saved with `masks add`):")
            for k, w in saved.items():
                n = int(masks.count_bits(w))
                print(f"  {k:<28} {100 * n / db.n_frames:5.1f}%  {db.mask_definitions[k]}")
    return 0
