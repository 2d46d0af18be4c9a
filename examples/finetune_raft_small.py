"""Fine-tune RAFT-small on frame pairs of which a fraction get random snow, as the paper retrains RAFT.

The paper (Section 4.3) retrains RAFT with RAFT's own recipe on Sintel-final with 0 %, 50 % or
100 % of the pairs snowy and finds 50 % best for robustness, quality and generalisation. This
script follows that protocol, scaled down by options: RAFT's sequence loss (``--gamma``), AdamW
with the one-cycle schedule, gradient clipping at 1, random crops and flips *after* the weather,
batch-norm statistics frozen. On the bundled demo scene and a CPU, a few dozen steps take minutes::

    python examples/finetune_raft_small.py --checkpoint raft-small --steps 40

With these defaults the snow is the paper's preset at its density per pixel area (3000 flakes per
1024x436 frame scaled to the demo's 384x176: 454 per pair), and RAFT-small learns from it. Measured
with the released weights (``--checkpoint raft-small``, shipped with the package) and exactly the command above, on one
CPU thread (51 s of CPU time): EPE on the four fixed pairs before training 0.884 px clean and
2.319 px with weather; after the 40 steps 0.475 px clean and 1.176 px with weather. (The paper's
3000 flakes unscaled, ``--set count=3000``, take the weather EPE to 40.4 px before training and
6.3 px after.)

and on Sintel, at the scale of the authors' Sintel stage (on a GPU)::

    python examples/finetune_raft_small.py --checkpoint raft-small --dataset sintel \\
        --root /data/MPI-Sintel --pass final --steps 100000 --batch-size 6 --crop 368 768 \\
        --gamma 0.85 --device cuda --weather-on device --workers 6 --out runs/snow50

The weather is drawn per (seed, epoch, index): rerunning gives the same batches, whatever
``--workers``. ``--weather-on workers`` renders it per pair in the DataLoader's worker processes,
``--weather-on device`` draws the particles in the workers and renders each batch in one call on
``--device``. Each step prints the training loss; before the first step and after the last, the
loss and EPE on a fixed set of pairs (``--eval-pairs``, clean and with weather) are printed too.
``--out`` writes the fine-tuned weights (``raft-small-finetuned.pth``, loadable with ``--checkpoint``) and ``log.csv``.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from weathergen.datasets import open_dataset
from weathergen.errors import WeatherGenError
from weathergen.models import available_checkpoints, build_model, checkpoint_spec, read_state_dict
from weathergen.models.checkpoints import resolve_named
from weathergen.training import (SINTEL_STAGE, Compose, PairDataset, RandomCrop, RandomFlip,
                                  WeatherAugment, collate_pairs, crop_pair, end_point_error,
                                  freeze_batch_norm, raft_optimizer, sequence_loss, train_step)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="RAFT-small weights to start from: a file, or the name raft-small (the "
                        "released weights, shipped with the package); "
                        "without it the network starts from random weights")
    p.add_argument("--dataset", default="demo", help="demo, sintel, kitti, spring or custom")
    p.add_argument("--root", default=None, help="where the dataset is stored (not for demo)")
    p.add_argument("--pass", dest="pass_", default="final", help="Sintel pass")
    p.add_argument("--steps", type=int, default=40, help="optimisation steps")
    p.add_argument("--batch-size", type=int, default=2,
                   help=f"pairs per step (RAFT's Sintel stage: {SINTEL_STAGE['batch_size']})")
    p.add_argument("--crop", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="random crop after the weather (RAFT's Sintel stage: 368 768); "
                        "default: the largest multiple of 8 that fits the frames, at most 368 768")
    p.add_argument("--iters", type=int, default=12, help="RAFT refinement iterations")
    p.add_argument("--lr", type=float, default=SINTEL_STAGE["lr"], help="peak learning rate")
    p.add_argument("--wdecay", type=float, default=SINTEL_STAGE["weight_decay"],
                   help="AdamW weight decay")
    p.add_argument("--gamma", type=float, default=0.8, help="sequence-loss decay")
    p.add_argument("--snowy", type=float, default=0.5, help="fraction of pairs with weather")
    p.add_argument("--preset", action="append", default=None,
                   help="weather preset (repeatable; default snow)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="change a preset key, e.g. --set count=1000")
    p.add_argument("--seed", type=int, default=1234,
                   help="seed of every random draw (the paper's snowy training set used 1234)")
    p.add_argument("--workers", type=int, default=0, help="DataLoader worker processes")
    p.add_argument("--weather-on", choices=("workers", "device"), default="workers",
                   help="render the weather per pair in the loader, or per batch on --device")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N")
    p.add_argument("--eval-pairs", type=int, default=4,
                   help="pairs (centre crops, clean and with weather) on which the loss is "
                        "printed before and after training")
    p.add_argument("--out", type=Path, default=None, help="folder for the weights and log.csv")
    return p.parse_args(argv)


def crop_size(dataset: PairDataset, wanted) -> tuple[int, int]:
    h, w = dataset[0].pair.size
    if wanted is not None:
        return tuple(wanted)
    return min(SINTEL_STAGE["crop"][0], h // 8 * 8), min(SINTEL_STAGE["crop"][1], w // 8 * 8)


def load_network(checkpoint, iters: int, device) -> torch.nn.Module:
    model = build_model("raft-small", iters=iters)
    if checkpoint in available_checkpoints("raft-small"):     # a name: the shipped or cached file
        checkpoint = resolve_named(checkpoint_spec(checkpoint))
    if checkpoint is not None:
        model.load_checkpoint(read_state_dict(checkpoint), source=checkpoint, what="raft-small")
    model.requires_grad_(True)
    return model.to(device)


def evaluation_batches(reader, count: int, crop, weather: WeatherAugment, device) -> dict:
    """The first ``count`` pairs, centre-cropped, clean and with weather drawn for epoch -1 (an
    epoch training never uses): a fixed yardstick for the loss."""
    data = PairDataset(reader)
    clean, snowy = [], []
    for i in range(min(count, len(data))):
        s = replace(data[i], epoch=-1)
        h, w = s.pair.size
        top, left = (h - crop[0]) // 2, (w - crop[1]) // 2
        clean.append(replace(s, pair=crop_pair(s.pair, top, left, crop[0], crop[1])))
        rendered = weather(s)
        snowy.append(replace(rendered, pair=crop_pair(rendered.pair, top, left, crop[0], crop[1])))
    return {"clean": collate_pairs(clean).to(device), "weather": collate_pairs(snowy).to(device)}


def evaluate(model, batches: dict, gamma: float) -> dict:
    """Sequence loss and EPE of ``model`` on each yardstick batch."""
    model.eval()
    out = {}
    with torch.no_grad():
        for name, batch in batches.items():
            p = batch.pairs
            flows = model.flow_sequence(p.image1, p.image2)
            out[name] = {"loss": float(sequence_loss(flows, p.flow, p.flow_valid, gamma=gamma)),
                         "epe": float(end_point_error(flows[-1], p.flow, p.flow_valid))}
    return out


def report(when: str, scores: dict) -> None:
    parts = [f"{name} loss {v['loss']:.4f} EPE {v['epe']:.3f} px" for name, v in scores.items()]
    print(f"{when}: " + ";  ".join(parts))


def main(argv=None) -> dict:
    args = parse_args(argv)
    device = torch.device(args.device)
    torch.manual_seed(args.seed)      # the network's own random initialisation, if any

    reader = open_dataset(args.dataset, args.root, pass_=args.pass_)
    bad = [item for item in args.overrides if "=" not in item]
    if bad:
        raise WeatherGenError(f"--set {bad[0]!r}: expected KEY=VALUE")
    overrides = dict(item.split("=", 1) for item in args.overrides)
    weather = WeatherAugment(args.preset or ["snow"], p=args.snowy, seed=args.seed,
                             overrides=overrides)
    probe = PairDataset(reader)
    crop = crop_size(probe, args.crop)
    geometric = [RandomCrop(crop, seed=args.seed), RandomFlip(0.5, 0.1, seed=args.seed)]
    if args.weather_on == "workers":     # weather, crop and flip per pair in the workers
        data, on_device = PairDataset(reader, Compose([weather, *geometric])), None
    else:                                # workers draw particles; the device renders batches
        data, on_device = PairDataset(reader, weather.prepare), Compose([weather, *geometric])
    order = torch.Generator().manual_seed(args.seed)
    loader = DataLoader(data, batch_size=args.batch_size, shuffle=True, drop_last=True,
                        num_workers=args.workers, collate_fn=collate_pairs, generator=order)
    if len(loader) == 0:
        raise WeatherGenError(f"{len(data)} pairs are fewer than one batch of {args.batch_size}")

    model = load_network(args.checkpoint, args.iters, device)
    optimizer, scheduler = raft_optimizer(model, args.steps, lr=args.lr, weight_decay=args.wdecay)
    all_weather = WeatherAugment(args.preset or ["snow"], p=1.0, seed=args.seed,
                                 overrides=overrides)
    yardstick = evaluation_batches(reader, args.eval_pairs, crop, all_weather, device)
    before = evaluate(model, yardstick, args.gamma)
    print(f"fixed pairs: {len(yardstick['clean'])} clean, the same with weather")
    report("before", before)

    log, step, epoch = [], 0, 0
    start = time.perf_counter()
    while step < args.steps:
        data.set_epoch(epoch)            # new weather, crops and flips every epoch
        for batch in loader:
            batch = batch.to(device)
            if on_device is not None:
                batch = on_device.apply_batch(batch)
            model.train()
            freeze_batch_norm(model)
            p = batch.pairs
            stats = train_step(model, optimizer, scheduler, p.image1, p.image2, p.flow,
                               p.flow_valid, gamma=args.gamma)
            snowy = sum(w is not None and w.applied for w in batch.weather)
            step += 1
            log.append({"step": step, "epoch": epoch, "loss": stats["loss"], "epe": stats["epe"],
                        "weather": snowy, "lr": scheduler.get_last_lr()[0],
                        "seconds": time.perf_counter() - start})
            print(f"step {step:5d}  epoch {epoch:3d}  loss {stats['loss']:.4f}  "
                  f"EPE {stats['epe']:.3f}  weather {snowy}/{len(batch)}", flush=True)
            if step >= args.steps:
                break
        epoch += 1

    after = evaluate(model, yardstick, args.gamma)
    report("after ", after)
    print(f"{args.steps} steps in {time.perf_counter() - start:.0f} s")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        torch.save(model.network.state_dict(), args.out / "raft-small-finetuned.pth")
        with open(args.out / "log.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(log[0]))
            writer.writeheader()
            writer.writerows(log)
        print(f"wrote {args.out / 'raft-small-finetuned.pth'} and {args.out / 'log.csv'}")
    return {"before": before, "after": after, "log": log}


if __name__ == "__main__":
    try:
        main()
    except WeatherGenError as exc:
        sys.exit(f"error: {exc}")
