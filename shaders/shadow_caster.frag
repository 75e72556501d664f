// The shadow-map pass writes depth only: the rasteriser stores it, nothing else is needed.
void main() {
}
