"""`gesturedb keywords DB.h5 {list,add,show,remove,drop,export}`: keyword sub-databases.

A keyword sub-database holds the stretches of the database around every
occurrence of a word (Habibie et al. 2022, Sec. 4.2); during synthesis the steps
that overlap the word in the input transcript take their gesture from it.
"""
from __future__ import annotations

import gesturedb
from gesturedb.errors import ParameterError
from gesturedb.io.outputs import check_outputs


def add_parser(sub) -> None:
    p = sub.add_parser(
        "keywords",
        help="list, add, inspect, edit and export keyword sub-databases",
        description="Keyword sub-databases: when a keyword is said in the input speech, the gesture for it is "
        "taken from the stretches of the database where the speaker said the same word.",
    )
    p.add_argument("db", metavar="DB.h5")
    acts = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    a = acts.add_parser("list", help="the sub-databases and the most frequent words of the database")
    a.add_argument("--top", type=int, default=20, help="how many frequent words to show (default: %(default)s)")

    a = acts.add_parser("add", help="create the sub-databases of words from all their occurrences (one edit)")
    a.add_argument("words", metavar="WORD", nargs="*", help="one or more keywords, added in one edit of the file")
    a.add_argument("--from", dest="from_file", metavar="FILE", default=None,
                   help="also add the words of FILE (one per line, '#' comments), in the same edit")
    a.add_argument("--before", type=float, default=0.5, dest="before_s",
                   help="seconds kept before the word (default: %(default)s)")
    a.add_argument("--after", type=float, default=1.0, dest="after_s",
                   help="seconds kept after the word (default: %(default)s)")
    a.add_argument("--replace", action="store_true", help="rebuild an existing sub-database of the word")

    a = acts.add_parser("show", help="the occurrences of a word with the words around them")
    a.add_argument("word", metavar="WORD")
    a.add_argument("--context", type=int, default=3, help="words shown on each side (default: %(default)s)")

    a = acts.add_parser("remove", help="take occurrences (numbered as by `show`) out of a sub-database")
    a.add_argument("word", metavar="WORD")
    a.add_argument("index", type=int, metavar="INDEX", nargs="+",
                   help="one or more occurrences, all numbered as `show` lists them before this edit")

    a = acts.add_parser("drop", help="delete a whole sub-database")
    a.add_argument("word", metavar="WORD")

    a = acts.add_parser("export", help="write a sub-database as a database file of its own")
    a.add_argument("word", metavar="WORD")
    a.add_argument("-o", "--output", required=True, metavar="OUT.h5")
    a.add_argument("--chunk-frames", type=int, default=None,
                   help="fixed chunks of this many frames within each occurrence (default: one chunk per occurrence)")
    p.set_defaults(run=run)


def _fmt_sub(sub, fps: float) -> str:
    return (f"{sub.word:<16} {len(sub):4d} occurrence(s)  {sub.n_frames / fps:7.1f} s  "
            f"({sub.before_s:g} s before, {sub.after_s:g} s after)")


def _list(args) -> int:
    from gesturedb.db import keywords as kw

    with gesturedb.open(args.db) as db:
        subs = kw.subdatabases(db)
        rows = kw.list_words(db, top=args.top)
        fps = db.fps
        n_words = len(db.words)
    if subs:
        print(f"{len(subs)} keyword sub-database(s):")
        for s in subs.values():
            print("  " + _fmt_sub(s, fps))
    else:
        print("no keyword sub-databases")
    if not rows:
        print("the database has no words (built without transcripts)")
        return 0
    print(f"most frequent of {n_words} words (* = has a sub-database):")
    width = max(len(r.word) for r in rows)
    for r in rows:
        mark = "*" if r.word in subs else " "
        print(f" {mark}{r.word:<{width}}  {r.count:5d} x  {r.total_s:7.2f} s")
    return 0


def _show(args) -> int:
    from gesturedb.db import keywords as kw

    with gesturedb.open(args.db) as db:
        subs = kw.subdatabases(db)
        rows = kw.show(db, args.word, n_context=args.context)
        fps = db.fps
    w = kw.normalise_word(args.word)
    if w in subs:
        print("sub-database " + _fmt_sub(subs[w], fps))
    else:
        print(f"{w!r} has no sub-database yet; `add` would collect these {len(rows)} occurrence(s):")
    width = max(len(r.recording) for r in rows)
    for r in rows:
        print(f"  {r.index:4d}  {r.recording:<{width}}  {r.time_s:8.2f} s  {r.context}")
    return 0


def run(args) -> int:
    from gesturedb.db import keywords as kw
    from gesturedb.db.export import export_keyword

    if args.action == "list":
        return _list(args)
    if args.action == "show":
        return _show(args)
    if args.action == "add":
        words = list(args.words) + (kw.read_word_list(args.from_file) if args.from_file else [])
        if not words:
            raise ParameterError("add: expected at least one WORD or --from FILE, got neither")
        added = kw.add_keywords(args.db, words, before_s=args.before_s, after_s=args.after_s, replace=args.replace)
        for a in added:
            print(f"added to {args.db}: {a.word!r}, {a.occurrences} occurrence(s), {a.n_frames} frames"
                  + (f" ({a.skipped} skipped: outside the motion)" if a.skipped else ""))
        return 0
    if args.action == "remove":
        sub = kw.remove_occurrence(args.db, args.word, args.index)
        which = ", ".join(map(str, sorted(set(args.index))))
        print(f"removed occurrence {which} of {sub.word!r} from {args.db}; {len(sub)} left")
        return 0
    if args.action == "drop":
        sub = kw.drop_keyword(args.db, args.word)
        print(f"dropped {sub.word!r} ({len(sub)} occurrence(s)) from {args.db}")
        return 0
    if args.action == "export":
        check_outputs({"-o": args.output}, [args.db])
        with export_keyword(args.db, args.word, args.output, chunk_frames=args.chunk_frames) as out:
            print(f"wrote {args.output}: {len(out.recordings)} recording(s), {out.n_frames} frames "
                  f"({out.n_frames / out.fps:.1f} s at {out.fps:g} fps), {len(out.words)} words")
        return 0
    raise AssertionError(f"unhandled action {args.action!r}")  # argparse restricts the choices
