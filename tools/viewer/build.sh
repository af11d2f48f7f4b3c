#!/bin/sh
# Rebuild pages/viewer/three.bundle.min.js: three.js with its orbit controls and glTF loader,
# from the npm registry (versions pinned in package.json and package-lock.json), bundled into
# one script that defines the global THREE (a page opened from disk cannot import modules).
set -e
cd "$(dirname "$0")"
npm ci --no-audit --no-fund
npx esbuild entry.js --bundle --minify --format=iife --global-name=THREE --legal-comments=eof \
    --outfile=../../pages/viewer/three.bundle.min.js
