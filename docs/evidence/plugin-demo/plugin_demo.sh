#!/bin/bash
# A plugin changed and rerun from the command line; the conformance check on a broken copy.
set -u
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 MFTCN_BENCH_HOME=/tmp/h-pdemo
rm -rf /tmp/pdemo /tmp/h-pdemo; mkdir -p /tmp/pdemo
PY=/work/main/.venv/bin/python
$PY -m pip install --quiet --no-deps --no-build-isolation --target /tmp/pdemo/site /work/main/examples/mftcn-bench-example-encoder
cd /work/test-tree
export PYTHONPATH=/work/test-tree:/tmp/pdemo/site
run() { echo "\$ mftcn-bench run --encoder pixel-pca --task cartpole-probe --preset smoke"; $PY -m mftcn_bench.cli run --encoder pixel-pca --task cartpole-probe --preset smoke --no-progress 2>&1 | grep -E "run [0-9a-f]{16}|Average|error"; }
echo "## 1. as installed (example 0.1.0)"; run
echo "## 2. the same again (reused)"; run
SRC=/tmp/pdemo/site/example_encoder/encoder.py
sed -i 's|grey = frames\[:, :, :: self.step, :: self.step\].mean(axis=-1) / 255.0|grey = frames[:, :, :: self.step, :: self.step, 1] / 255.0  # changed: the green channel only|' $SRC
grep -n "changed" $SRC
echo "## 3. source changed (green channel only), same version"; run
sed -i 's/^Version: 0.1.0/Version: 0.1.1/' /tmp/pdemo/site/mftcn_bench_example_encoder-0.1.0.dist-info/METADATA
echo "## 4. version bumped to 0.1.1, same source"; run
echo "## 5. the record names the plugin"; $PY -c "
import json,glob
for p in sorted(glob.glob('/tmp/h-pdemo/runs/*/result.json')):
    r=json.load(open(p)); c=r['config']['code']['encoder']
    print(r['run_id'], c['distribution'], c['version'], c['source'], round(r['metrics']['average'],4))"
echo "## 6. a broken copy: embed returns float64"
sed -i 's|return self.pca.transform(self._features(clips.frames)).astype(np.float32)|return self.pca.transform(self._features(clips.frames))  # broken: float64|' $SRC
$PY -m mftcn_bench.cli check encoder pixel-pca 2>&1; echo "exit $?"
