#!/bin/bash
# The A/B of stop 47 (docs/results.md): an unmodified `cat` (preload, frames) under TMR, killed
# by the injector, with the preload library before (base: without the spare line renewal in
# `write`) and after (new), alternated run by run with the same seeds. desc.json is the
# description, SEED and TAG filled in per run; release build of 7b20a7b.
# ab.sh REPS: alternate base/new preload libraries under the same release bootstrap
cd /tmp/p47; mkdir -p out
for r in $(seq 1 $1); do
  for v in base new; do
    tag=$v-$r
    sed "s/SEED/$r/; s/TAG/$tag/" desc.json > d-$tag.json
    S3RES_PRELOAD=/tmp/p47/$v/libs3res_preload.so RUST_LOG=info,s3res_voter::recovery=debug /tmp/p47/tgt/release/s3res-bootstrap -q d-$tag.json > out/boot-$tag.out 2> out/boot-$tag.err
    echo "$tag rc=$?" >> out/runs.log
  done
done
