// AudioWorklet of the gesturedb studio: passes its input through unchanged and posts
// blocks of mono samples (the first channel) to the page, which sends them to the server.
// Blocks of about 40 ms: small enough for a live stream, large enough not to flood the socket.
class Capture extends AudioWorkletProcessor {
  constructor(options) {
    super();
    this.size = (options && options.processorOptions && options.processorOptions.blockSamples) || 2048;
    this.buf = new Float32Array(this.size);
    this.n = 0;
    this.port.onmessage = (e) => { if (e.data === 'flush') this.flush(); };
  }
  flush() {
    if (this.n > 0) {
      this.port.postMessage(this.buf.slice(0, this.n));
      this.n = 0;
    }
  }
  process(inputs, outputs) {
    const input = inputs[0];
    const output = outputs[0];
    for (let c = 0; c < output.length; c++) {
      if (input[c]) output[c].set(input[c]);
    }
    const x = input[0];
    if (x) {
      let i = 0;
      while (i < x.length) {
        const k = Math.min(x.length - i, this.size - this.n);
        this.buf.set(x.subarray(i, i + k), this.n);
        this.n += k;
        i += k;
        if (this.n === this.size) this.flush();
      }
    }
    return true;
  }
}
registerProcessor('gesturedb-capture', Capture);
