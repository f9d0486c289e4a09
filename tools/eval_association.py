#!/usr/bin/env python3
"""Scores `instgs-vk segment --per-frame-ids` against the key of tools/scramble_masks.py: every
associated instance should gather the masks of exactly one true instance, one per view. Prints
purity and completeness per instance and writes OUT_LABELS.json, the labels renumbered to the
true ids (majority of the instance's masks), for `instgs-vk instance` against ground truth.

usage: eval_association.py LABELS.json KEY.json SPLIT OUT_LABELS.json
"""
import collections, json, sys

labels_path, key_path, split, out_path = sys.argv[1:]
doc = json.load(open(labels_path))
key = json.load(open(key_path))[split]
views = len(key)
true_of = {}
ok = True
for g in doc["groups"]:
    for inst in g["instances"]:
        truths = collections.Counter(key[name.rsplit(".", 1)[0]][str(mid)] for name, mid in inst["masks"])
        t, n = truths.most_common(1)[0]
        true_of[inst["id"]] = t
        masks = sum(truths.values())
        print(f"{g['name']} {inst['id']}: {masks} masks -> true instance {t} ({n}/{masks} pure, "
              f"{masks}/{views} views)")
        ok &= len(truths) == 1
trues = sorted(true_of.values())
print(f"instances recovered: {len(trues)}, true ids {trues}, all pure: {ok}, one per true id: {len(set(trues)) == len(trues)}")
doc["labels"] = [true_of.get(l, 0) if l else 0 for l in doc["labels"]]
doc["ids"] = [true_of[i] for i in doc["ids"]]
del doc["groups"]
json.dump(doc, open(out_path, "w"))
