// The codecs' and the section encodings' reading rules, written by omg4.codec.coders.browser_module from
// their tables (CODERS, omg4.codec.encodings.ENCODINGS): regenerate, do not edit.
export const CODERS = {
  "compact": {
    "name": "compact",
    "index_encodings": [
      "ranks",
      "first-use"
    ],
    "morton_positions": true,
    "grid_encodings": true,
    "quaternion_sections": true
  },
  "ans": {
    "name": "ans",
    "index_encodings": [
      "ans"
    ],
    "morton_positions": true,
    "grid_encodings": false,
    "quaternion_sections": false
  },
  "paper": {
    "name": "paper",
    "index_encodings": [
      "paper"
    ],
    "morton_positions": false,
    "grid_encodings": false,
    "quaternion_sections": false
  }
};

export const ENCODINGS = {
  "reference": {
    "pattern": "reference",
    "sections": [
      "codebook",
      "mlp",
      "matrix"
    ],
    "needs": null
  },
  "delta-weights": {
    "pattern": "delta-int([2-8])-cols",
    "sections": [
      "matrix"
    ],
    "needs": "grid_encodings"
  },
  "ans": {
    "pattern": "ans",
    "sections": [
      "index"
    ],
    "needs": "index_encodings"
  },
  "ranks": {
    "pattern": "ranks",
    "sections": [
      "index"
    ],
    "needs": "index_encodings"
  },
  "first-use": {
    "pattern": "first-use",
    "sections": [
      "index"
    ],
    "needs": "index_encodings"
  },
  "paper": {
    "pattern": "paper",
    "sections": [
      "index"
    ],
    "needs": "index_encodings"
  },
  "quaternions": {
    "pattern": "smallest-three-([2-9]|1[0-5])",
    "sections": [
      "quat"
    ],
    "needs": null
  },
  "sorted": {
    "pattern": "sorted",
    "sections": [
      "codebook"
    ],
    "needs": "grid_encodings"
  },
  "weights": {
    "pattern": "int([2-8])-(rows|cols)",
    "sections": [
      "matrix"
    ],
    "needs": "grid_encodings"
  },
  "morton": {
    "pattern": "morton",
    "sections": [
      "xyz"
    ],
    "needs": "morton_positions"
  },
  "grid-positions": {
    "pattern": "grid-morton|grid-morton-exact",
    "sections": [
      "xyz"
    ],
    "needs": "grid_encodings"
  },
  "grid-times": {
    "pattern": "grid",
    "sections": [
      "t"
    ],
    "needs": "grid_encodings"
  },
  "f16": {
    "pattern": "f16|f16-lzma|f16-planes",
    "sections": [
      "xyz",
      "t",
      "codebook",
      "mlp",
      "matrix"
    ],
    "needs": null
  }
};
