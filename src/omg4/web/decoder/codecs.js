// The codecs' reading rules, written by omg4.codec.coders.browser_module from its table (CODERS):
// regenerate, do not edit.
export const CODERS = {
  "compact": {
    "indexEncodings": [
      "ranks",
      "first-use"
    ],
    "mortonPositions": true,
    "gridEncodings": true,
    "quaternionSections": true
  },
  "ans": {
    "indexEncodings": [
      "ans"
    ],
    "mortonPositions": true,
    "gridEncodings": false,
    "quaternionSections": false
  },
  "paper": {
    "indexEncodings": [
      "paper"
    ],
    "mortonPositions": false,
    "gridEncodings": false,
    "quaternionSections": false
  }
};
