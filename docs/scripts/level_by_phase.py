"""Where a model's brightness level goes wrong with the viewing geometry: for each `g2r-train eval` output
directory, the crops grouped by ground (terrain class and unit under their centre) and by phase angle band, with the
learned / paper-Hapke SSE of the group, the mean level (a method's mean brightness over the ground truth's) of the
learned model and of `oracle_model_form`
(the truth's own maps fitted by the run's model form: the best any network of that form can render), and their
crop counts. A level that falls with phase in both says the model form cannot follow the truth's angular shape
there; a gap between them in every band says the fit falls short of what the form allows.

    python docs/scripts/level_by_phase.py EVAL_DIR...

"learned" is the network alone (`learned_network`) where the run keeps a crater level.
"""
import json
import sys
from collections import defaultdict

PHASE_BANDS_DEG = [(0, 25), (25, 40), (40, 55), (55, 180)]

for evaluation in sys.argv[1:]:
    metrics = json.load(open(f"{evaluation}/metrics.json"))
    groups = defaultdict(list)
    for image in metrics["per_image"]:
        unit = "highland" if image["highland"] >= 0.5 else "mare"
        groups[(image["terrain_class"], unit)].append(image)
    print(evaluation)
    print("  ground: per phase band " + ", ".join(f"{a}-{b} deg" for a, b in PHASE_BANDS_DEG) + ": learned / form-oracle level (crops)")
    for (ground, unit), images in sorted(groups.items()):
        learned = "learned_network" if "learned_network" in images[0]["level"] else "learned"
        cells = []
        for low, high in PHASE_BANDS_DEG:
            band = [im for im in images if low <= im["phase_deg"] < high]
            if not band:
                cells.append("-")
                continue
            mean = lambda key: sum(im["level"][key] for im in band) / len(band)
            cells.append(f"{mean(learned):.3f} / {mean('oracle_model_form'):.3f} ({len(band)})")
        total = lambda key: sum(im["level"][key] for im in images) / len(images)
        sse = lambda key: sum(im["metrics"][key]["sse"] for im in images)
        print(
            f"  {ground} {unit}: {len(images)} crops, learned / paper-Hapke {sse(learned) / sse('hapke_paper'):.3f}, "
            f"level learned {total(learned):.3f}, form-oracle "
            f"{total('oracle_model_form'):.3f}, oracle {total('oracle'):.3f}; by phase " + ", ".join(cells)
        )
