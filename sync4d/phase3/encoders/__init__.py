"""Phase 3's image-text encoders behind one interface (`encoder`: `Encoder`, `load_encoder`):
`siglip` (the paper's SigLIP through onnxruntime, exported by users with internet) and
`offline` (the closed-vocabulary default: AlexNet features mapped into `minilm`'s sentence
space, fitted on the generated renders of `shapes`). Modules are imported on use: a query
whose texts are cached loads none of them.
"""
