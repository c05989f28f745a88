#!/usr/bin/python3
"""The neural asset's driven textures at full resolution against the simulator's truth (docs/asset.md#driving-the-textures).

Usage: asset_full_textures.py ASSET_DIR FULL_INFER_DIR NET_INFER_DIR [SIZE]

ASSET_DIR holds dataset.h5 (with its dataset-neutral/ textures) and ref.h5, a dataset of the same take's truth at
SIZE texels (512; `stage-process asset build-dataset --texture-size SIZE --neutral-texture-size -1 --output
ASSET_DIR/ref.h5`); FULL_INFER_DIR is `asset infer`'s output with the neutral textures, NET_INFER_DIR one at the
net's size (a dataset without them). On the held-out-block frames, over the truth's valid texels: albedo RMS in sRGB
levels and the normals' mean angle of the full-resolution textures, beside two baselines of the same run: the
net-size textures upsampled bilinearly, and the neutral frame's full-resolution textures. Reads OpenEXR through
oiiotool (Python here has no OpenEXR module) and h5py.
"""
import h5py, numpy as np, subprocess, sys, os, tempfile, torch, re
if len(sys.argv) < 4:
    sys.exit(__doc__)
T, FULL, NET = sys.argv[1:4]
SIZE = int(sys.argv[4]) if len(sys.argv) > 4 else 512
ref = h5py.File(T + '/ref.h5'); ds = h5py.File(T + '/dataset.h5')
assert list(ref['frame'][:]) == list(ds['frame'][:])
split = ds['split'][:]; frames = ds['frame'][:]

def exr(path, channels=('R', 'G', 'B')):
    out = os.path.join(tempfile.gettempdir(), 'asset_full_textures.fits')
    subprocess.run(['oiiotool', path, '--ch', ','.join(channels), '-d', 'float', '-o', out], check=True)
    raw = open(out, 'rb').read()
    h = 0
    while True:
        block = raw[h:h + 2880].decode('ascii'); h += 2880
        if any(block[i:i + 80].startswith('END ') or block[i:i + 80].strip() == 'END' for i in range(0, 2880, 80)): break
    hdr = raw[:h].decode('ascii')
    ax = [int(re.search(r'NAXIS%d\s*=\s*(\d+)' % k, hdr).group(1)) for k in (1, 2, 3)]
    c, w, hh = ax
    data = np.frombuffer(raw[h:h + 4 * c * w * hh], dtype='>f4').reshape(hh, w, c)
    return np.roll(data[::-1], 1, axis=0)  # OIIO 2.4 writes FITS rows bottom to top, one row off (checked below)

def srgb(x):
    x = np.clip(x, 0, 1); return 255 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)

def up(img, size):
    t = torch.from_numpy(np.ascontiguousarray(img.astype('<f4'))).permute(2, 0, 1)[None].float()
    return torch.nn.functional.interpolate(t, size=(size, size), mode='bilinear', align_corners=False)[0].permute(1, 2, 0).numpy()

neutral_a = exr(T + '/dataset-neutral/albedo.exr')
neutral_n = exr(T + '/dataset-neutral/normal_tangent.exr')
print('orientation check, neutral vs ref frame 0: max |d albedo| =',
      np.abs(neutral_a - ref['textures'][0][..., :3])[ref['texture_valid'][0] > 0].max())
rows = {'driven, full resolution': [], 'driven at the net size, upsampled': [], 'neutral frame, full resolution': []}
nrm = {k: [] for k in rows}
for i in np.where(split == 1)[0]:
    f = frames[i]; truth = ref['textures'][i]; valid = ref['texture_valid'][i] > 0
    full_a = exr(FULL + '/frame-%06d/albedo.exr' % f)
    full_n = exr(FULL + '/frame-%06d/normal_tangent.exr' % f)
    net_a = up(exr(NET + '/frame-%06d/albedo.exr' % f), SIZE)
    net_n = up(exr(NET + '/frame-%06d/normal_tangent.exr' % f), SIZE)
    for k, a, n in [('driven, full resolution', full_a, full_n), ('driven at the net size, upsampled', net_a, net_n),
                    ('neutral frame, full resolution', neutral_a, neutral_n)]:
        rows[k].append(((srgb(a) - srgb(truth[..., :3]))[valid] ** 2).mean())
        nn = n / np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-9)
        tt = truth[..., 4:7] / np.maximum(np.linalg.norm(truth[..., 4:7], axis=2, keepdims=True), 1e-9)
        nrm[k].append(np.degrees(np.arccos(np.clip((nn * tt).sum(2), -1, 1)))[valid].mean())
print('%d held-out-block frames, %d texels valid in frame 0' % ((split == 1).sum(), (ref['texture_valid'][0] > 0).sum()))
for k in rows:
    print('%-36s albedo %.3f levels RMS, normals %.3f deg mean' % (k, np.sqrt(np.mean(rows[k])), np.mean(nrm[k])))
