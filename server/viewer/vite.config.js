// Build the live viewer into dist/ (served by the voxfusion server at /sessions/<id>/view, assets under
// /viewer/assets/). `make viewer` runs this; dist/ is committed so the server needs no Node.js.
import { defineConfig } from 'vite';

export default defineConfig({
  base: '/viewer/',
  build: {
    outDir: 'dist',
    emptyOutDir: true,
    assetsDir: 'assets',
    chunkSizeWarningLimit: 1024,
    sourcemap: false,
  },
});
