"""Training RE-Net weights: recipes, data, losses, the loop, checkpoints, DDP.

- :mod:`.recipe` — TOML recipe → frozen, validated :class:`~.recipe.Recipe`;
- :mod:`.data` — ``data`` paths → datasets (image folders simulated on the fly, trmd HDF5
  sets, the paper's GOPRO h5), the held-out split, a resumable sampler;
- :mod:`.losses` — registry of ``loss(outputs, batch, recipe)`` callables (the paper's
  residual + middle MSE; blur and event consistency need no ground truth);
- :mod:`.loop` — :func:`~.loop.train`; :mod:`.steps` — one step, validation, checkpoint;
- :mod:`.checkpoint` — atomic safetensors checkpoints, no pickle;
- :mod:`.plots` — the training curve PNG; :mod:`.ddp` — torchrun / DistributedDataParallel.

Nothing is imported here, so ``import trmd_cli.train`` stays free of torch.
"""
