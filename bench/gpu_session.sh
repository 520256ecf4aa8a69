#!/usr/bin/env bash
# The prepared device check for a session that is lent a GPU: the CUDA tests, the training / sampling throughput
# on CUDA, and a timed TrajFlow training of the ETH/UCY fold eth with the paper's settings for a few epochs, from
# which the paper protocol's GPU time can be estimated. One command, about 5-8 minutes, so that it fits one call
# of the `device` tool (10 minutes) with time to rerun it.
#
#   bash bench/gpu_session.sh prepare    # here, once: wheels the GPU image lacks into .whl/, data/eth_ucy ingested
#   rm -rf docs/results                  # here: the published models (about 100 MB) would put the tree over the
#                                        # 64 MiB a call carries; `git checkout -- docs/results` brings them back
#   bash bench/gpu_session.sh run        # there: device run, carry [".whl", "data/eth_ucy"], timeout_s 560
#
# The first GPU session (2026-12-04, bench/README "ninth round") ran it in 136 s of command time (plus about 30 s to
# start the machine); the step profile added since takes about a minute more.
#
# The GPU image has torch, numpy 2, scipy, scikit-learn, pyarrow, typer, rich, matplotlib and safetensors, but not
# polars or zuko; nothing can be downloaded there, so those travel as wheels (about 55 MB of the 64 MiB a
# call may carry). The package runs from the checkout on PYTHONPATH (`python3 -m trajflow_pipeline`), not
# installed, so that pip leaves the image's own packages as they are.
# Logs go to $OUT (the device tool brings them back). A dry run of `run` on a CPU machine checks the script itself:
#   OUT=/tmp/out DEVICE=cpu EPOCHS=1 bash bench/gpu_session.sh run
set -euo pipefail
cd "$(dirname "$0")/.."

WHEELS=(polars==2.1.0 polars-runtime-32==2.1.0 zuko==1.6.0)

prepare() {
    rm -rf .whl && mkdir -p .whl
    for wheel in "${WHEELS[@]}"; do
        python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
            --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
            -d .whl "$wheel"
    done
    [ -f data/eth_ucy/dataset.json ] || trajflow ingest eth-ucy ../shared/data/eth_ucy -o data/eth_ucy
    du -sh .whl data/eth_ucy
}

run() {
    : "${OUT:?run this through the device tool, which sets OUT}"
    local device=${DEVICE:-cuda} epochs=${EPOCHS:-3}
    export PYTHONUNBUFFERED=1
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH="/tmp/site:$PWD"
    local tf=(python3 -m trajflow_pipeline)
    python3 -c 'import torch, numpy, polars; print("torch", torch.__version__, "cuda", torch.version.cuda,
        torch.cuda.is_available() and torch.cuda.get_device_name(0), "numpy", numpy.__version__,
        "polars", polars.__version__)' | tee "$OUT/gpu.txt"

    echo "== CUDA tests"
    TRAJFLOW_DATA= python3 -m pytest -q -p no:cacheprovider tests/model/test_cuda.py tests/model/test_runtime_threads.py \
        > "$OUT/tests.txt" 2>&1 || echo "TESTS FAILED: the figures below still come"
    tail -5 "$OUT/tests.txt"

    if [ "$device" = cuda ]; then
        echo "== training / sampling throughput on CUDA"
        timeout 150 python3 bench/train.py --no-cpu --repeats 3 --models trajflow flomo 2>&1 | tee "$OUT/bench_train.txt"
        echo "== where a flow step's time goes on CUDA; the GRUs' two paths side by side"
        timeout 150 python3 bench/step_profile.py --gru-rounds 3 --batches 128 2048 --no-compile 2>&1 \
            | grep -v USDT | tee "$OUT/step_profile.txt"
    fi

    echo "== ETH/UCY fold eth, TrajFlow, paper settings, $epochs autoencoder + $epochs flow epochs on $device"
    local run_dir=/tmp/eth_fold
    rm -rf "$run_dir"
    "${tf[@]}" train data/eth_ucy -o "$run_dir" --fold eth --model trajflow --device "$device" -q \
        --set train.ae_max_epochs="$epochs" --set train.ae_min_epochs=0 --set train.flow_max_epochs="$epochs" \
        --set train.flow_min_epochs=0
    python3 -c 'import polars as pl, sys; pl.Config.set_tbl_rows(20)
print(pl.read_parquet(sys.argv[1]).select("stage", "epoch", "seconds", "samples_per_s", "val_loss"))' \
        "$run_dir/train_log.parquet" | tee "$OUT/eth_epochs.txt"
    echo "== its evaluation: 100 draws on $device, ROME on $(nproc) CPU workers"
    local metrics=(--metric min_ade --metric min_fde --metric min_ade_joint --metric min_fde_joint --metric nll
                   --metric nll_joint)
    local start=$SECONDS
    "${tf[@]}" eval "$run_dir" "${metrics[@]}" --device "$device" --workers "$(nproc)" -q
    echo "evaluation wall time: $((SECONDS - start)) s" | tee "$OUT/eth_eval_time.txt"
    cp "$run_dir/run.json" "$run_dir/eval/eval.json" "$OUT/"
}

case "${1:-}" in
    prepare) prepare ;;
    run) run ;;
    *) echo "usage: bash bench/gpu_session.sh prepare|run" >&2; exit 2 ;;
esac
