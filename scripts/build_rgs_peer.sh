#!/usr/bin/env bash
# Build "rgs_peer": a command-line wrapper around the published C++ implementation
# of Zheng et al.'s radial-gradient-symmetry vignetting estimator
# (VignettingCorrectionUsingRG, github.com/GUOYI1/Vignetting_corrector,
# C++/Vig_Correction/), for use as a comparison peer in benchmarks.
#
# Usage: scripts/build_rgs_peer.sh SNAPSHOT_REPO_DIR OUT_DIR
#   SNAPSHOT_REPO_DIR  a git dir (bare or not) or a plain checkout of that repository
#   OUT_DIR            receives the executable OUT_DIR/rgs_peer
# Needs g++ (no OpenCV). The peer's sources are extracted into a temporary build
# directory and deleted afterwards: none of the peer's code is ever committed to
# this repository; only the small driver below (our own code) lives here.
#
# Licence caveat: the upstream repository states no licence for its C++ code
# (the README only credits Zheng for the Matlab part). Build and use it locally for
# benchmarking only; do not redistribute the binary or the extracted sources.
#
# Driver CLI:  rgs_peer IN.pgm OUT.pfm [PROFILE.txt]
#   IN.pgm   8-bit binary PGM (P5, maxval <= 255), grey, W x H.
#   OUT.pfm  estimated vignetting ATTENUATION field (observed = scene * field), at
#            the full W x H, grey PFM ("Pf", scale -1.0 = little-endian float32,
#            rows stored bottom-to-top as the PFM format specifies).
#            NB: OpenImageIO 3.2 reads PFM rows in file order without flipping
#            (its writer does flip), so read it with numpy and flip: a[::-1].
#            Normalised to 1 at the image centre (radius bin 0), exactly as the
#            authors' main does (vp /= vp[0]); values elsewhere may exceed 1.
#   PROFILE.txt (optional) one line per radius bin r of the working image:
#            "r  log_vp[r]  vp[r]/vp[0]".
#   stdout: nothing; stderr: the routine's own "WLS..." chatter plus a summary line.
#   Exit status non-zero on bad input or if the routine reports failure.
# What the driver replicates from the authors' Windows/OpenCV main (Vig_Correction.cpp):
#   - resize to width 75 (if W > 75; ratio = 75/W, h = int(H*ratio+0.5)) with
#     cvResize's default bilinear interpolation (reimplemented here after
#     OpenCV 2.x's fixed-point INTER_LINEAR for 8-bit: half-pixel centres, edge
#     clamp, 11-bit coefficients, rounding), then run the routine on that copy;
#   - vp = exp(vp) / exp(vp[0]);
#   - per full-resolution pixel: r = (sqrt(dx^2+dy^2) + 0.5) * ratio with
#     dx = i - int(W/2), dy = j - int(H/2); n = int(r); field = vp[0] if n == 0,
#     vp[n-1]*(1-(r-n)) + vp[n]*(r-n) if n < len(vp), else vp[last]; the authors
#     then divide each pixel by that value, so it is the attenuation.
set -euo pipefail

if [ $# -ne 2 ]; then
    echo "usage: $0 SNAPSHOT_REPO_DIR OUT_DIR" >&2
    exit 2
fi
snap="$1"
out="$2"
sub="C++/Vig_Correction"
files="ColorCorrection.cpp ColorCorrection.hpp Matrix.cpp Matrix.h commondata.h commonfile.h"

command -v g++ >/dev/null || { echo "g++ not found (apt-get install g++)" >&2; exit 1; }

build="$(mktemp -d)"
trap 'rm -rf "$build"' EXIT

# --- extract the peer's sources -------------------------------------------------
if [ -f "$snap/$sub/ColorCorrection.cpp" ]; then
    mkdir -p "$build/$sub"
    for f in $files; do cp "$snap/$sub/$f" "$build/$sub/"; done
elif git -C "$snap" rev-parse --git-dir >/dev/null 2>&1; then
    git -C "$snap" archive HEAD "$sub" | tar -x -C "$build"
else
    echo "$snap: neither a checkout nor a git dir holding $sub" >&2
    exit 1
fi
src="$build/$sub"
for f in $files; do
    [ -f "$src/$f" ] || { echo "missing $sub/$f in snapshot" >&2; exit 1; }
done
# include names that differ only in case from the files (written on Windows)
ln -sf commondata.h "$src/Commondata.h"
ln -sf commondata.h "$src/CommonData.h"
ln -sf Matrix.h "$src/matrix.h"

# --- our driver ------------------------------------------------------------------
cat > "$build/main.cpp" <<'EOF'
// rgs_peer driver (vigproc's own code): PGM in, attenuation-field PFM out.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>
#include <unistd.h>

int VignettingCorrectionUsingRG(unsigned char* pImage, int ht, int wd,
                                std::vector<double>& vp);

static int die(const std::string& m) { std::fprintf(stderr, "rgs_peer: %s\n", m.c_str()); return 1; }

static bool read_token(FILE* f, int& v) {
    int c = std::fgetc(f);
    while (c != EOF) {
        if (c == '#') { while (c != EOF && c != '\n') c = std::fgetc(f); }
        else if (c == ' ' || c == '\t' || c == '\n' || c == '\r') c = std::fgetc(f);
        else break;
    }
    if (c < '0' || c > '9') return false;
    long x = 0;
    while (c >= '0' && c <= '9') { x = x * 10 + (c - '0'); if (x > 1000000) return false; c = std::fgetc(f); }
    v = (int)x;  // c is the single whitespace byte after the token (consumed)
    return true;
}

static bool read_pgm(const char* path, int& w, int& h, std::vector<unsigned char>& px) {
    FILE* f = std::fopen(path, "rb");
    if (!f) return false;
    char m[2];
    int maxv = 0;
    bool ok = std::fread(m, 1, 2, f) == 2 && m[0] == 'P' && m[1] == '5' &&
              read_token(f, w) && read_token(f, h) && read_token(f, maxv) &&
              w > 0 && h > 0 && maxv > 0 && maxv <= 255;
    if (ok) {
        px.resize((size_t)w * h);
        ok = std::fread(px.data(), 1, px.size(), f) == px.size();
    }
    std::fclose(f);
    return ok;
}

// OpenCV 2.x cv::resize INTER_LINEAR for 8-bit, scalar path (what cvResize does by default).
struct Tap { int i; short a0, a1; };
static std::vector<Tap> taps(int ssz, int dsz) {
    std::vector<Tap> t(dsz);
    double scale = (double)ssz / dsz;
    for (int d = 0; d < dsz; d++) {
        float fx = (float)((d + 0.5) * scale - 0.5);
        int sx = (int)std::floor(fx);
        fx -= sx;
        if (sx < 0) { fx = 0; sx = 0; }
        if (sx >= ssz - 1) { fx = 0; sx = ssz - 1; }
        long a0 = std::lround((1.f - fx) * 2048), a1 = std::lround(fx * 2048);
        t[d] = {sx, (short)a0, (short)a1};
    }
    return t;
}
static void resize_linear(const unsigned char* s, int sw, int sh, unsigned char* d, int dw, int dh) {
    std::vector<Tap> tx = taps(sw, dw), ty = taps(sh, dh);
    std::vector<int> r0(dw), r1(dw);
    auto hrow = [&](int y, std::vector<int>& r) {
        const unsigned char* row = s + (size_t)y * sw;
        for (int x = 0; x < dw; x++) {
            int i = tx[x].i, i1 = i + 1 < sw ? i + 1 : sw - 1;
            r[x] = row[i] * tx[x].a0 + row[i1] * tx[x].a1;
        }
    };
    for (int y = 0; y < dh; y++) {
        int j = ty[y].i, j1 = j + 1 < sh ? j + 1 : sh - 1;
        hrow(j, r0); hrow(j1, r1);
        for (int x = 0; x < dw; x++) {
            int v = (r0[x] * ty[y].a0 + r1[x] * ty[y].a1 + (1 << 21)) >> 22;
            d[(size_t)y * dw + x] = (unsigned char)(v < 0 ? 0 : v > 255 ? 255 : v);
        }
    }
}

int main(int argc, char** argv) {
    if (argc != 3 && argc != 4)
        return die("usage: rgs_peer IN.pgm OUT.pfm [PROFILE.txt]");
    int wd = 0, ht = 0;
    std::vector<unsigned char> img;
    if (!read_pgm(argv[1], wd, ht, img))
        return die(std::string("cannot read 8-bit binary PGM (P5) ") + argv[1]);

    // As in the authors' VignettingCorrect(): work on a copy 75 pixels wide.
    double ratio = 1;
    if (wd > 75) ratio = 75.0 / double(wd);
    int sht = ht * ratio + 0.5;
    int swd = wd * ratio + 0.5;
    if (sht < 2 || swd < 2) return die("image too small");
    std::vector<unsigned char> small((size_t)sht * swd);
    if (sht == ht && swd == wd) small = img;
    else resize_linear(img.data(), wd, ht, small.data(), swd, sht);

    // The routine prints to stdout; keep our stdout clean.
    std::fflush(stdout);
    int saved = dup(1);
    dup2(2, 1);
    std::vector<double> vp;
    int flag = VignettingCorrectionUsingRG(small.data(), sht, swd, vp);
    std::fflush(stdout);
    dup2(saved, 1);
    close(saved);
    if (flag != 0 || vp.empty()) return die("VignettingCorrectionUsingRG failed");

    int nV = vp.size();
    std::vector<double> logvp = vp;
    for (int i = 0; i < nV; i++) vp[i] = std::exp(vp[i]);
    double maxVr = vp[0];
    for (int i = 0; i < nV; i++) vp[i] = vp[i] / maxVr;

    if (argc == 4) {
        FILE* p = std::fopen(argv[3], "w");
        if (!p) return die(std::string("cannot write ") + argv[3]);
        for (int i = 0; i < nV; i++) std::fprintf(p, "%d %.10g %.10g\n", i, logvp[i], vp[i]);
        std::fclose(p);
    }

    // Full-resolution field, exactly the authors' per-pixel lookup.
    int halfHt = ht * 0.5, halfWd = wd * 0.5;
    std::vector<float> field((size_t)wd * ht);
    for (int j = 0; j < ht; j++)
        for (int i = 0; i < wd; i++) {
            double cx = i - halfWd, cy = j - halfHt;
            double radius = (std::sqrt(cx * cx + cy * cy) + 0.5) * ratio;
            double v;
            int nR = int(radius);
            if (nR == 0) v = vp[0];
            else if (nR < nV) { double dr = radius - nR; v = vp[nR - 1] * (1 - dr) + vp[nR] * dr; }
            else v = vp[nV - 1];
            field[(size_t)j * wd + i] = (float)v;
        }

    FILE* o = std::fopen(argv[2], "wb");
    if (!o) return die(std::string("cannot write ") + argv[2]);
    std::fprintf(o, "Pf\n%d %d\n-1.0\n", wd, ht);
    bool ok = true;
    for (int j = ht - 1; j >= 0 && ok; j--)  // PFM: bottom row first
        ok = std::fwrite(&field[(size_t)j * wd], sizeof(float), wd, o) == (size_t)wd;
    ok = (std::fclose(o) == 0) && ok;
    if (!ok) return die(std::string("write failed: ") + argv[2]);
    std::fprintf(stderr, "rgs_peer: %dx%d -> working %dx%d, %d radius bins, field min %.4f\n",
                 wd, ht, swd, sht, nV, *std::min_element(field.begin(), field.end()));
    return 0;
}
EOF

# --- compile -----------------------------------------------------------------------
# Shims: -fpermissive (Matrix.h declares sss/ppp non-static, Matrix.cpp defines them
# static), _declspec defined away, <cstring> for memset in ColorCorrection.cpp,
# --gc-sections to drop Matrix.cpp helpers (PCA/Jacobi) that need commonfile.cpp,
# which includes the Windows-only <io.h> and is therefore not compiled.
mkdir -p "$out"
cxx_peer=(g++ -O2 -std=c++11 -w -fpermissive -ffunction-sections -fdata-sections
          "-D_declspec(x)=" "-D__declspec(x)=" -include cstring -I "$src")
"${cxx_peer[@]}" -c "$src/ColorCorrection.cpp" -o "$build/ColorCorrection.o"
"${cxx_peer[@]}" -c "$src/Matrix.cpp" -o "$build/Matrix.o"
g++ -O2 -std=c++11 -Wall -ffunction-sections -fdata-sections \
    -c "$build/main.cpp" -o "$build/main.o"
g++ -O2 -Wl,--gc-sections "$build/main.o" "$build/ColorCorrection.o" "$build/Matrix.o" \
    -o "$out/rgs_peer"
echo "built $out/rgs_peer"
