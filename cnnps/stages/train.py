"""Stage ``train``: fit CNN-PS (or the network of ``model``) on the extract stage's output.

Reads ``data_dir/extract/manifest.json`` (or ``data.shards``: a path or an fsspec URL, the
extract stage's ``output``) and streams the ``train`` shards through
:class:`cnnps.io.shards.ShardStream` (row groups shuffled per epoch, a shuffle buffer;
the data never has to fit in memory), or, from an extract of ``layout: observations``,
b x b patches drawn from the per-pixel observation files (b = ``model.patch``,
:mod:`cnnps.train.observation_data`; batches seeded by (seed, epoch, batch)). The network
is ``model``'s (``arch``, ``head``, ``patch``: :class:`cnnps.train.params.ModelParams`,
the paper's CNN-PS by default). Loss: the head's (MSE between the predicted and the true
unit normal for ``regression``, :func:`cnnps.models.heads.training_loss`); Adam. Validation (mean / median angular error in degrees over up to
``val_max_rows`` maps of the ``val`` scenes, each map on its own, no rotation
averaging, through the batched inference of ``cnnps predict``, always in fp32) runs every
``val_every`` steps and at the end.

The stage's ``Params`` (nested: ``optimiser``, ``data``, ``pixelwise``, ``cpu``, ``model``, and
``synthesis``, filled from ``materials`` and ``extract``) is :class:`cnnps.train.params.Params`,
the typed tree the training loop reads too; this module holds the run key and :func:`run`;
the machinery is in
:mod:`cnnps.train` (:mod:`~cnnps.train.loop`, :mod:`~cnnps.train.optimiser`,
:mod:`~cnnps.train.resume`, :mod:`~cnnps.train.validation`,
:mod:`~cnnps.train.distributed`, and the CPU and GPU speed modules named below).

Resuming: every ``checkpoint_every`` steps (and at the end) ``data_dir/train/
checkpoints/step-NNNNNNNN.pt`` is written atomically with model, optimiser, torch RNG
states, the step (= loader position: the batch order of an epoch is a function of
(seed, epoch)) and the metric history. :func:`run` continues from the newest checkpoint
whose run key (:func:`run_key`: the params that change the result, the manifest hash and
the ``init`` weights' SHA-256) matches, so a killed run resumed to N steps ends with the
weights of an uninterrupted one. ``epochs``, ``max_steps`` and the logging/checkpoint
intervals are not part of the key: raising ``max_steps`` or ``epochs`` continues a
finished run.

Learning rate: ``optimiser.lr`` times ``optimiser.lr_gamma`` at each step of
``optimiser.lr_milestones`` (:func:`cnnps.train.optimiser.lr_at`, independent of
``max_steps``). ``init`` names a cnnps checkpoint whose weights replace the random
initialisation (fine-tuning); its weights' SHA-256 is recorded in the model's meta
(``init_weights_sha256``).

Weight averaging: with ``optimiser.average_from: N`` (N >= 1) ``model.pt`` holds the mean
of the weights at every checkpoint from step N on (:mod:`cnnps.train.averaging`; the mean
travels in the checkpoints, so a resume reaches the same one), and the final validation
and ``val_mean_deg`` are the mean's (``metrics.json``'s ``average`` also gives the last
step's). With ``optimiser.ema_decay: d`` it is instead the exponential moving average
e <- d e + (1 - d) w over every step (in the checkpoints too; one of the two).

Phases: with ``phases`` (:mod:`cnnps.train.phase_params`) the run is a sequence of
phases, each a run as above in ``data_dir/train/phases/kk-name/`` of its own steps and
changed settings, from the weights the phase before it ended with or from a weighted mean
of earlier phases' weights; ``model.pt`` is the last phase's (:mod:`cnnps.train.phases`:
resuming, the keys, the outputs). ``epochs`` and ``max_steps`` are then unused.

Several processes: under ``torchrun`` (``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``), e.g.
``torchrun --standalone --nproc-per-node 4 -m cnnps run-stage train``, every process
trains a DistributedDataParallel replica (NCCL on GPUs, ``cuda:LOCAL_RANK``; gloo on CPU).
``data.batch_size`` stays the global batch: each of the N ranks takes ``batch_size / N``
rows a step (it must divide) from its own disjoint share of every epoch's row groups, and
every rank runs the same number of steps per epoch. Only rank 0 validates and writes
checkpoints, plots, metrics and the model; a checkpoint holds every rank's RNG state, so a
resume with the same number of processes is exact. The logged loss is the mean over ranks.

How a step runs (none of these changes the model or the loss; they change float
rounding): ``precision`` (``auto``: chosen once, at the run's first step, from this
machine's cached answer or a probe timing fp32 and bf16 steps where the device has bf16
kernels; every resume, step process and rank keeps it; the run key holds the precision
chosen, :mod:`cnnps.train.precision`; ``metrics.json`` and ``model.pt`` record it),
``channels_last``, ``compile`` (opt-in torch.compile, eager with a warning when it fails),
``optimiser.fused_adam``; on a CPU :func:`run` sets ``OMP_WAIT_POLICY=PASSIVE`` before
torch loads unless the environment sets a policy (:mod:`cnnps.train.openmp`), and
``cpu.dropout_masks`` (counter-based masks keyed by the step: resume-exact with no RNG
state), ``cpu.layers`` (:mod:`cnnps.models.train_layers`), ``cpu.keep_freed_memory``
(:mod:`cnnps.train.allocator`) and ``cpu.step_processes`` (helper processes computing
part of each batch's rows, :mod:`cnnps.train.step_processes`; masks drawn per 16-row
block, so the weights are one process's up to float rounding and the setting is not in
the run key) apply. On CUDA, batches go through pinned buffers
(:mod:`cnnps.train.device_feed`) and the loss is read every ``log_every`` steps only.
Per-pixel maps (``pixelwise.share``) are made ``pixelwise.ahead`` steps ahead
(:mod:`cnnps.train.maps_ahead`) from a generator seeded by the step, so they are the same
made ahead or in the step. What each setting costs or gains: ``docs/performance.md``.

What per-pixel maps are drawn from: the material categories and BSDF ranges of
``materials.categories`` / ``materials.ranges`` and the light subsets of
``extract.min_lights``, ``max_lights``, ``cone_min_deg``, ``cone_max_deg`` and
``sparse_min_lights``, the settings the renders and shards are made with
(:class:`SynthesisParams`, filled by the config layer); their own settings are
``pixelwise.lights`` (the light set's size), ``pixelwise.sparse_fraction`` and
``pixelwise.effects``. ``docs/pipeline.md`` has the table of which setting feeds which data.

Colour maps (``pixelwise.rgb: true``, with ``pixelwise.share: 1``): the network takes
(B, 4, w, w) maps, the grey map then R, G, B (:func:`cnnps.synth.pixelwise.generate` with
``rgb=True``), validation maps too; a grey ``init`` is widened to 4 input channels with
the colour filters at 0 (:func:`cnnps.models.network.widen_state`), a colour one loads
as it is. The eager CPU layers run (the fused first convolution is for one channel).

Outputs: ``data_dir/train/model.pt`` (``cnnps.models.checkpoint.save_checkpoint``; config w,
dropout, in_channels and the model options off their defaults; meta steps, val error, manifest hash), ``metrics.json`` (with the loop's time
split, :mod:`cnnps.train.step_clock`: waiting for data, validation, checkpoints),
``plots/loss.csv`` (step, loss) and ``plots/val.csv`` (step, val_mean_deg,
val_median_deg) for ``dvc plots``.
"""

from __future__ import annotations

from pathlib import Path

from cnnps.infra.hashing import stable_hash
from cnnps.train.openmp import prefer_passive_openmp  # torch-free (torch loads in run)
from cnnps.train.params import (  # the stage's typed params (torch-free), re-exported for the config layer
    FROM_SECTIONS,
    MOVED_KEYS,
    OMITTED_AT_DEFAULT,
    SECTIONS,
    CpuParams,
    DataParams,
    OptimiserParams,
    Params,
    PixelwiseParams,
    SynthesisParams,
)

__all__ = ["FROM_SECTIONS", "MOVED_KEYS", "OMITTED_AT_DEFAULT", "SECTIONS", "CpuParams",
           "DataParams", "OptimiserParams", "Params", "PixelwiseParams", "SynthesisParams", "run", "run_key"]


def run_key(params: Params, manifest_sha256: str, init_sha256: str | None = None, precision: str | None = None) -> str:
    """The key a checkpoint must carry to be resumed: a hash of the params that change the
    result (:meth:`Params.result_key`) with the precision the run steps in (``precision``:
    ``train.precision: auto`` resolved, :mod:`cnnps.train.precision`; an ``auto`` run that
    stepped in fp32 has the key of an ``fp32`` run, one that stepped in bf16 a ``bf16``
    run's), the manifest's SHA-256 and, with ``init``, the SHA-256 of the starting weights."""
    d = params.result_key()
    d["precision"] = precision or params.precision
    if d["precision"] not in ("fp32", "bf16"):
        raise ValueError(f"a run key needs the precision the run steps in (fp32 or bf16), not {d['precision']!r}")
    return stable_hash([d, manifest_sha256] + ([init_sha256] if init_sha256 else []), compact=False)


def run(params: Params, data_dir: Path, *, until=None, _stop_after_step: int | None = None) -> dict:
    """Train; returns the final metrics. ``until(step) -> bool``, asked after every step,
    ends the run early and normally (e.g. a CPU-time budget; the number of steps then
    depends on the clock). ``_stop_after_step`` (tests only) raises ``KeyboardInterrupt``
    after that step, like a killed run.

    Under torchrun (``WORLD_SIZE`` > 1) this process is one rank of a
    DistributedDataParallel job (see the module docstring); the process group is
    set up here unless the caller already did.
    """
    prefer_passive_openmp()  # before torch loads (the import below)
    from cnnps.train import loop
    from cnnps.train.init_weights import load_init_weights
    from cnnps.train.pixelwise_batches import input_channels, pixelwise_maker
    from cnnps.train.process_setup import training_processes
    from cnnps.train.training_data import open_training_data, pixelwise_only_data

    data_dir = Path(data_dir)

    def open_data(p: Params):
        if p.pixelwise.share >= 1.0:
            return pixelwise_only_data(p.pixelwise.w)  # no shards at all
        return open_training_data(p.data.shards or data_dir / "extract")

    def load_init(p: Params, data):
        return load_init_weights(p.init, data.w, input_channels(p), p.model.options())

    def train_one(p: Params, data, out_dir: Path, init_state, init_sha, stop, until_):
        return loop.train(p, data, out_dir, lambda precision: run_key(p, data.manifest_sha256, init_sha, precision),
                          info, device, init_state, init_sha, stop_after_step=stop, until=until_)

    def validate_only(p: Params, data, out_dir: Path, init_state, init_sha):  # a phase of 0 steps
        t = loop.Trainer(p, data, out_dir, lambda precision: run_key(p, data.manifest_sha256, init_sha, precision),
                         info, device, init_state, init_sha)
        t.make_pixelwise, t.precision = pixelwise_maker(p), "fp32"
        t.load_validation()
        return t.finish()

    with training_processes(params) as (info, device):
        if params.phases:
            from cnnps.train.phases import run_phases

            return run_phases(params, data_dir, info, device, open_data=open_data, load_init=load_init,
                              train_one=train_one, validate_only=validate_only, stop_after_step=_stop_after_step,
                              until=until)
        data = open_data(params)
        return train_one(params, data, data_dir / "train", *load_init(params, data), _stop_after_step, until)
